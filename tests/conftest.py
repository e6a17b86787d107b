"""Test tiers: default (CPU, minutes), ``-m slow`` (long verification), ``-m gpu`` (needs CUDA)."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(scope="session", autouse=True)
def _one_torch_thread():
    """Tests run torch single-threaded: two OpenMP threads on a 2-core machine that is also running
    Warp kernels or a data worker oversubscribe the cores and run several times slower."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip_gpu = pytest.mark.skip(reason="needs CUDA, and this machine has no GPU")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip_gpu)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """Ten synthetic assets with 32 px views (train/val/test all point at them in tests)."""
    from physgm.data.synth import SynthConfig, generate

    root = tmp_path_factory.mktemp("tiny_dataset") / "synthetic"
    cfg = SynthConfig(count=10, seed=11, resolution=32, gaussians=600, video_fraction=0.0)
    summary = generate(cfg, root, workers=1, progress=False)
    assert summary["failed"] == 0, summary["failures"]
    return root
