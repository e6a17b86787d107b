"""Fixtures for the pipeline tests: a tiny random checkpoint, small run settings, test inputs.

Runs are tiny (32 px, 6 frames) so the whole folder stays fast on a 2-core CPU.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from tests.model_configs import small_config

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"


@pytest.fixture(scope="session")
def tiny_ckpt(tmp_path_factory) -> Path:
    """A randomly initialised small PhysGM saved in the LitPretrain checkpoint layout."""
    from physgm.model import PhysGM
    from physgm.model.checkpoint import save_checkpoint

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("ckpt") / "tiny.ckpt"
    save_checkpoint(PhysGM(small_config(), load_pretrained=False), path)
    return path


@pytest.fixture
def make_cfg(tiny_ckpt, tmp_path):
    """RunConfig with tiny output settings; keyword arguments replace fields (``output__frames``: nested)."""
    from physgm.pipeline.config import OutputSettings, RunConfig

    def make(input, **kw):
        cfg = RunConfig(
            input=Path(input),
            output_dir=tmp_path / "run",
            ckpt=tiny_ckpt,
            output=OutputSettings(resolution=32, frames=6, keyframes=3, progress=False),
        )
        for key, value in kw.items():
            *parents, name = key.split("__")
            obj = cfg
            for part in parents:
                obj = getattr(obj, part)
            setattr(obj, name, value)
        cfg.validate()
        return cfg

    return make


@pytest.fixture
def blob_ply(tmp_path) -> Path:
    """A 3DGS .ply of an ellipsoid of Gaussians (0.6 x 0.4 x 0.3 units), +z up."""
    from physgm.gaussians import Gaussians, write_ply

    gen = torch.Generator().manual_seed(1)
    n = 600
    x = torch.randn(n, 3, generator=gen)
    x = x / x.norm(dim=1, keepdim=True) * torch.rand(n, 1, generator=gen) ** (1 / 3)
    means = x * torch.tensor([0.3, 0.2, 0.15]) + torch.tensor(
        [5.0, -2.0, 1.0]
    )  # off-centre, like a real capture
    g = Gaussians(
        means,
        torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        torch.full((n, 3), 0.03),
        torch.full((n,), 0.9),
        torch.rand(n, 3, generator=gen),
    )
    path = tmp_path / "blob.ply"
    write_ply(g, path)
    return path


@pytest.fixture(name="examples")
def _examples() -> Path:
    return EXAMPLES


@pytest.fixture(name="png_with_size_header")
def _png_with_size_header():
    return png_with_size_header


@pytest.fixture(name="rgba_png")
def _rgba_png():
    return rgba_png


def png_with_size_header(path: Path, width: int, height: int) -> Path:
    """A PNG whose header claims width x height but holds no pixel data (a decompression-bomb stand-in)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + kind
            + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
        )

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b""))
    return path


def rgba_png(path: Path, size: int = 48, alpha_value: int = 255, disc: bool = True) -> Path:
    from PIL import Image

    yy, xx = np.mgrid[:size, :size]
    inside = (yy - size / 2) ** 2 + (xx - size / 2) ** 2 < (size / 3) ** 2
    img = np.zeros((size, size, 4), np.uint8)
    img[..., 0], img[..., 1], img[..., 2] = 200, 60, 40
    img[..., 3] = np.where(inside if disc else True, alpha_value, 0)
    Image.fromarray(img).save(path)
    return path
