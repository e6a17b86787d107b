"""Shared fixtures for the model tests: the small model config (``tests.model_configs``) and a batch of
posed views."""

from __future__ import annotations

import pytest
import torch

from physgm.cameras import orbit_cameras
from tests.model_configs import small_config


def make_batch(b: int, v: int, height: int, width: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random images, disc-plus-noise masks and orbit cameras around the origin."""
    gen = torch.Generator().manual_seed(seed)
    images = torch.rand(b, v, 3, height, width, generator=gen)
    yy, xx = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    disc = ((yy - height / 2) ** 2 + (xx - width / 2) ** 2 < (0.35 * min(height, width)) ** 2).float()
    masks = (disc + 0.3 * torch.rand(b, v, 1, height, width, generator=gen)).clamp(0, 1)
    c2w, Ks = [], []
    for i in range(b):
        az = (torch.arange(v) * 360.0 / v + 17.0 * i).tolist()
        cams = orbit_cameras(az, [15.0 + 5 * i] * v, radius=1.5, fov_deg=40.0, width=width, height=height)
        c2w.append(cams.c2w)
        Ks.append(cams.Ks)
    return {"images": images, "masks": masks, "c2w": torch.stack(c2w), "Ks": torch.stack(Ks)}


@pytest.fixture(autouse=True)
def _seed_and_one_thread():
    """Seed, and run single-threaded: these models are too small to gain from threads, and with
    other processes on the 2 cores the OpenMP threads wait on each other (a train step measured
    430 ms with 2 threads against 15 ms with 1)."""
    torch.manual_seed(0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(name="small_config")
def _small_config_fixture():
    return small_config


@pytest.fixture(name="make_batch")
def _make_batch_fixture():
    return make_batch
