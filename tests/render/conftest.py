"""Scene builders shared by the renderer tests (small sizes: the whole folder runs in ~1 min).

Helpers are handed out through the `kit` fixture (not imported), so the tests work under any
pytest import mode and never clash with other folders' conftest modules.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch


@pytest.fixture(autouse=True)
def _one_torch_thread():
    # Other jobs share the 2 cores; two OpenMP threads then stall on every small op, which
    # turns the torch reference from seconds into minutes. Results do not depend on it.
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """OpenCV world-to-camera matrix [4, 4] (x right, y down, z forward) looking at target."""
    eye_t = torch.tensor(eye, dtype=torch.float64)
    forward = torch.nn.functional.normalize(torch.tensor(target, dtype=torch.float64) - eye_t, dim=0)
    right = torch.nn.functional.normalize(
        torch.linalg.cross(forward, torch.tensor(up, dtype=torch.float64)), dim=0
    )
    down = torch.linalg.cross(forward, right)
    rot = torch.stack([right, down, forward])
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ eye_t
    return view


def intrinsics(focal: float, width: int, height: int) -> torch.Tensor:
    return torch.tensor(
        [[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float64
    )


def random_gaussians(n: int, seed: int, radius: float = 0.5, scale=(0.01, 0.06)) -> dict:
    """Gaussians in a ball like a small object: dict of means, quats, scales, opacities, colors."""
    gen = torch.Generator().manual_seed(seed)
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1)
    r = radius * torch.rand(n, 1, generator=gen, dtype=torch.float64) ** (1 / 3)
    log_lo, log_hi = math.log(scale[0]), math.log(scale[1])
    return {
        "means": direction * r,
        "quats": torch.randn(n, 4, generator=gen, dtype=torch.float64),
        "scales": torch.exp(
            log_lo + (log_hi - log_lo) * torch.rand(n, 3, generator=gen, dtype=torch.float64)
        ),
        "opacities": torch.rand(n, generator=gen, dtype=torch.float64),
        "colors": torch.rand(n, 3, generator=gen, dtype=torch.float64),
    }


def orbit_cameras(
    num: int, width: int, height: int, distance: float = 2.0, focal: float = 40.0, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """`num` cameras at `distance` from the origin looking at it: viewmats [C,4,4], Ks [C,3,3]."""
    gen = torch.Generator().manual_seed(seed + 1000)
    views = []
    for i in range(num):
        az = 2 * math.pi * i / max(num, 1) + 0.3 * float(torch.rand(1, generator=gen))
        el = 0.5 * (float(torch.rand(1, generator=gen)) - 0.5)
        eye = (
            distance * math.cos(el) * math.cos(az),
            distance * math.cos(el) * math.sin(az),
            distance * math.sin(el),
        )
        views.append(look_at(eye))
    K = intrinsics(focal, width, height)
    return torch.stack(views), K.expand(num, 3, 3).clone()


def to(scene: dict, dtype=torch.float32, requires_grad: bool = False) -> dict:
    """Copies every tensor of a scene to `dtype` as fresh leaves."""
    out = {}
    for key, value in scene.items():
        out[key] = (
            value.to(dtype).clone().requires_grad_(requires_grad and key in GRAD_KEYS)
            if isinstance(value, torch.Tensor)
            else value
        )
    return out


GRAD_KEYS = ("means", "quats", "scales", "opacities", "colors")


@pytest.fixture
def scene():
    """A 300-Gaussian object seen by 3 cameras at 40 x 32 px (float64 master copy)."""
    width, height = 40, 32
    viewmats, Ks = orbit_cameras(3, width, height)
    return {**random_gaussians(300, seed=0), "viewmats": viewmats, "Ks": Ks, "width": width, "height": height}


@pytest.fixture
def kit():
    """Scene helpers: look_at, intrinsics, random_gaussians, orbit_cameras, to, GRAD_KEYS."""
    return SimpleNamespace(
        look_at=look_at,
        intrinsics=intrinsics,
        random_gaussians=random_gaussians,
        orbit_cameras=orbit_cameras,
        to=to,
        GRAD_KEYS=GRAD_KEYS,
    )
