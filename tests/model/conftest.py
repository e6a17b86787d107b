"""Shared fixtures for the model tests: a very small config and a batch of posed views.

Exposed as fixtures (not imports) so they work under any pytest import mode.
"""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from physgm.cameras import orbit_cameras
from physgm.model import BackboneConfig, EncoderConfig, GaussianHeadConfig, PhysGMConfig


def small_config(**head) -> PhysGMConfig:
    """Smaller than the tiny default so that tests stay fast; same code paths."""
    encoder = EncoderConfig(img_size=32, patch_size=8, embed_dim=64, depth=1, num_heads=2)
    backbone = BackboneConfig(
        encoder=encoder,
        width=64,
        depth=4,
        head_dim=32,
        camera_dim=16,
        camera_hidden=32,
        out_layers=(0, 1, 2, 3),
    )
    gaussian_head = replace(
        GaussianHeadConfig(features=16, layer_channels=(16, 16, 32, 32), hidden=16), **head
    )
    return PhysGMConfig(backbone=backbone, gaussian_head=gaussian_head)


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
