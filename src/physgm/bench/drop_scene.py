"""The bench's drop scene: a hollow cube of Gaussians (a 3DGS-like shell), its camera, projection."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import torch

from physgm.cameras import Cameras, orbit_cameras
from physgm.gaussians import Gaussians
from physgm.physics.materials import PhysicsSpec, get_material


def hollow_cube_gaussians(n: int, side: float, bottom: float, seed: int = 0) -> Gaussians:
    """n Gaussians on the surface of a cube (like a 3DGS reconstruction: nothing inside)."""
    g = torch.Generator().manual_seed(seed)
    face = torch.randint(0, 6, (n,), generator=g)
    uv = torch.rand(n, 2, generator=g) - 0.5
    pts = torch.zeros(n, 3)
    axis, sign = face // 2, (face % 2) * 2 - 1.0
    for a in range(3):
        m = axis == a
        others = [b for b in range(3) if b != a]
        pts[m, a] = 0.5 * sign[m]
        pts[m, others[0]], pts[m, others[1]] = uv[m, 0], uv[m, 1]
    return Gaussians(
        means=pts * side + torch.tensor([0.0, 0.0, bottom + side / 2]),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        scales=torch.full((n, 3), side / 150),
        opacities=torch.full((n,), 0.9),
        colors=torch.rand(n, 3, generator=g),
    )


def bench_camera(side: float, bottom: float, width: int = 256) -> Cameras:
    """One 256 px camera framing the drop (object and ground)."""
    return orbit_cameras(
        [30.0],
        [15.0],
        radius=8 * side,
        fov_deg=40.0,
        width=width,
        height=width,
        target=(0.0, 0.0, 0.5 * (bottom + side)),
    )


def project(cameras: Cameras, x: torch.Tensor) -> torch.Tensor:
    """Pixel coordinates [..., 2] of world points [..., 3] in the first camera (all in front of it)."""
    view = cameras.viewmats[0].to(x)
    cam = x @ view[:3, :3].T + view[:3, 3]
    if not (cam[..., 2] > 0).all():
        raise ValueError("a point lies behind the camera: its pixel coordinates are not defined")
    uvw = cam @ cameras.Ks[0].to(x).T
    return uvw[..., :2] / uvw[..., 2:3]


@dataclass(frozen=True)
class DropBench:
    """The planned drops of ``python -m physgm.bench sim``: which materials fall, for how long, as
    which hollow cube (its ``scenes`` and ``options`` parts drop the same one)."""

    materials: tuple[str, ...]  # material table names, one drop each
    n_frames: int = 50  # output frames, the rest frame 0 included
    n_gaussians: int = 20_000  # Gaussians on the cube's surface
    side: float = 0.15  # cube side, m
    bottom: float = 0.5  # height of the cube's lowest face above the ground at the start, m
    E_override: Mapping[str, float] = field(default_factory=dict)  # material -> E (Pa), else the table's

    def gaussians(self) -> Gaussians:
        return hollow_cube_gaussians(self.n_gaussians, self.side, self.bottom)

    def camera(self) -> Cameras:
        return bench_camera(self.side, self.bottom)

    def physics(self, material: str) -> PhysicsSpec:
        return PhysicsSpec(material, E=self.E_override.get(material, get_material(material).E))

    def scene_overrides(self) -> dict[str, float]:
        """Keyword arguments of the registered "drop" scene: the cube starts at ``bottom``."""
        return {"height": self.bottom}
