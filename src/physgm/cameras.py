"""Pinhole cameras in the OpenCV convention, orbit cameras, and Plücker ray maps.

Conventions:
    camera frame: x right, y down, z forward (OpenCV);
    ``c2w``: camera-to-world 4x4; ``viewmats``: world-to-camera 4x4 (what renderers take);
    ``Ks``: 3x3 pixel intrinsics, pixel centres at integer + 0.5;
    world frame: right-handed, +z up, metres.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

# Flips y and z: OpenGL/Blender cameras look down -z with y up; OpenCV looks down +z with y down.
_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))


@dataclass
class Cameras:
    """C pinhole cameras sharing one image size.

    Attributes:
        c2w: [C, 4, 4] camera-to-world (OpenCV).
        Ks: [C, 3, 3] intrinsics in pixels.
        width, height: image size in pixels.
    """

    c2w: Tensor  # [C, 4, 4]
    Ks: Tensor  # [C, 3, 3]
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.c2w.ndim != 3 or self.c2w.shape[1:] != (4, 4):
            raise ValueError(f"Cameras.c2w must have shape [C, 4, 4], got {tuple(self.c2w.shape)}")
        if self.Ks.shape != (self.c2w.shape[0], 3, 3):
            raise ValueError(
                f"Cameras.Ks must have shape [C, 3, 3] with C = {self.c2w.shape[0]}, got "
                f"{tuple(self.Ks.shape)}"
            )
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"Cameras width and height must be positive, got {self.width} x {self.height}")
        if not (torch.isfinite(self.c2w).all() and torch.isfinite(self.Ks).all()):
            raise ValueError("Cameras contain non-finite values in c2w or Ks")

    def __len__(self) -> int:
        return self.c2w.shape[0]

    def __getitem__(self, index) -> Cameras:
        c2w, Ks = self.c2w[index], self.Ks[index]
        if c2w.ndim == 2:
            c2w, Ks = c2w[None], Ks[None]
        return Cameras(c2w, Ks, self.width, self.height)

    def to(self, device: torch.device | str) -> Cameras:
        return Cameras(self.c2w.to(device), self.Ks.to(device), self.width, self.height)

    @property
    def viewmats(self) -> Tensor:
        """World-to-camera matrices, [C, 4, 4]."""
        return invert_rigid(self.c2w)

    @property
    def centers(self) -> Tensor:
        """Camera centres in world space, [C, 3]."""
        return self.c2w[:, :3, 3]

    def resized(self, width: int, height: int) -> Cameras:
        """The same cameras for another image size (intrinsics scaled)."""
        sx, sy = width / self.width, height / self.height
        Ks = self.Ks.clone()
        Ks[:, 0] *= sx
        Ks[:, 1] *= sy
        return Cameras(self.c2w, Ks, width, height)


def invert_rigid(mats: Tensor) -> Tensor:
    """Inverse of rigid 4x4 transforms [..., 4, 4] (rotation transposed, no general inverse)."""
    rot = mats[..., :3, :3].transpose(-1, -2)
    out = torch.zeros_like(mats)
    out[..., :3, :3] = rot
    out[..., :3, 3] = -(rot @ mats[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1
    return out


def intrinsics_from_fov(fov_deg: float, width: int, height: int) -> Tensor:
    """Intrinsics [3, 3] with the given *horizontal* field of view and square pixels."""
    if not 0 < fov_deg < 180:
        raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg}")
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def look_at(eye: Tensor, target: Tensor, up: Tensor | None = None) -> Tensor:
    """OpenCV camera-to-world matrices looking from ``eye`` at ``target``.

    Args:
        eye: [C, 3] camera centres.
        target: [C, 3] points looked at.
        up: [3] world up (default +z); image "up" is its projection.
    Returns:
        [C, 4, 4].
    """
    up = torch.tensor([0.0, 0.0, 1.0], dtype=eye.dtype) if up is None else up.to(eye.dtype)
    forward = torch.nn.functional.normalize(target - eye, dim=-1)
    right = torch.linalg.cross(forward, up.expand_as(forward))
    # Looking straight up or down: any right vector perpendicular to forward will do.
    degenerate = right.norm(dim=-1) < 1e-8
    if degenerate.any():
        right[degenerate] = torch.linalg.cross(
            forward[degenerate], torch.tensor([0.0, 1.0, 0.0], dtype=eye.dtype).expand_as(forward[degenerate])
        )
    right = torch.nn.functional.normalize(right, dim=-1)
    down = torch.linalg.cross(forward, right)
    c2w = torch.eye(4, dtype=eye.dtype).repeat(eye.shape[0], 1, 1)
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = right, down, forward, eye
    return c2w


def orbit_cameras(
    azimuths_deg: Sequence[float] | Tensor,
    elevations_deg: Sequence[float] | Tensor,
    radius: float,
    fov_deg: float,
    width: int,
    height: int,
    target: Sequence[float] = (0.0, 0.0, 0.0),
) -> Cameras:
    """Cameras on a sphere around ``target``, looking at it.

    Position = target + radius * (cos el cos az, cos el sin az, sin el): azimuth 0 looks along -x,
    positive elevation is above the target.

    Args:
        azimuths_deg: [C] degrees.
        elevations_deg: [C] degrees (same length as azimuths).
        radius: distance to the target, m.
        fov_deg: horizontal field of view, degrees.
        width, height: image size, pixels.
        target: point looked at, m.
    """
    az = torch.as_tensor(azimuths_deg, dtype=torch.float32).reshape(-1)
    el = torch.as_tensor(elevations_deg, dtype=torch.float32).reshape(-1)
    if az.shape != el.shape:
        raise ValueError(
            f"azimuths_deg and elevations_deg must have the same length, got {az.numel()} and {el.numel()}"
        )
    if radius <= 0:
        raise ValueError(f"radius must be positive, got {radius}")
    az, el = torch.deg2rad(az), torch.deg2rad(el)
    tgt = torch.tensor(target, dtype=torch.float32).expand(az.shape[0], 3)
    eye = tgt + radius * torch.stack([el.cos() * az.cos(), el.cos() * az.sin(), el.sin()], -1)
    K = intrinsics_from_fov(fov_deg, width, height)
    return Cameras(look_at(eye, tgt), K.expand(az.shape[0], 3, 3).clone(), width, height)


def opengl_to_opencv(c2w: Tensor) -> Tensor:
    """Convert OpenGL/Blender camera-to-world matrices [..., 4, 4] to OpenCV ones."""
    if c2w.shape[-2:] != (4, 4):
        raise ValueError(f"c2w must have shape [..., 4, 4], got {tuple(c2w.shape)}")
    return c2w @ _GL_TO_CV.to(c2w)


def pixel_rays(cameras: Cameras) -> tuple[Tensor, Tensor]:
    """World-space ray origins and unit directions through pixel centres.

    Returns:
        origins [C, H, W, 3] and directions [C, H, W, 3].
    """
    c, h, w = len(cameras), cameras.height, cameras.width
    dtype, device = cameras.c2w.dtype, cameras.c2w.device
    v, u = torch.meshgrid(
        torch.arange(h, dtype=dtype, device=device) + 0.5,
        torch.arange(w, dtype=dtype, device=device) + 0.5,
        indexing="ij",
    )
    pix = torch.stack([u, v, torch.ones_like(u)], -1).reshape(1, -1, 3)  # [1, HW, 3]
    cam_dirs = pix @ torch.linalg.inv(cameras.Ks).transpose(-1, -2)  # [C, HW, 3]
    dirs = torch.nn.functional.normalize(cam_dirs @ cameras.c2w[:, :3, :3].transpose(-1, -2), dim=-1)
    origins = cameras.c2w[:, None, :3, 3].expand_as(dirs)
    return origins.reshape(c, h, w, 3), dirs.reshape(c, h, w, 3)


def plucker_rays(cameras: Cameras) -> Tensor:
    """Plücker ray map (direction, moment = origin x direction) per pixel, [C, 6, H, W]."""
    origins, dirs = pixel_rays(cameras)
    moments = torch.linalg.cross(origins, dirs, dim=-1)
    return torch.cat([dirs, moments], -1).permute(0, 3, 1, 2).contiguous()
