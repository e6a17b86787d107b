"""Test tiers: default (CPU, minutes), ``-m slow`` (long verification), ``-m gpu`` (needs CUDA)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


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


def _run_python(*args: str, timeout_s: float = 600) -> subprocess.CompletedProcess:
    """``python ARGS`` from the repository root, as a user types it (this checkout's src first).

    It gets its own process group, killed whole at the timeout: a training run may have spawned
    ranks or data workers, and a hung one ignores SIGTERM (Lightning traps it). A timeout fails the
    test with the tail of stderr."""
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        [sys.executable, *args],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"{' '.join(args)} did not finish in {timeout_s} s; stderr tail:\n{err[-3000:]}")
    return subprocess.CompletedProcess(args, proc.returncode, out, err)


@pytest.fixture(scope="session")
def run_python() -> Callable[..., subprocess.CompletedProcess]:
    """Runs ``python ARGS`` as a user would; see ``_run_python``."""
    return _run_python
