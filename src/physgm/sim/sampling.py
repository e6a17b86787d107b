"""Simulation particles from Gaussians, and Gaussians that follow the particles.

A reconstruction holds far more Gaussians than MPM needs (tens per grid cell, packed on the
surface), and nothing inside a hollow shell. We (1) drop near-transparent Gaussians, (2) keep one
particle per occupied voxel of side ``spacing`` at the centroid of the Gaussians in it, (3)
optionally fill the voxels enclosed by the surface (flood fill from the outside), and (4) let
every Gaussian follow its K nearest particles: its centre is the weighted first-order
extrapolation of the particles' motion, x_g = sum_j w_j (x_j + F_j (X_g - X_j)), and its
deformation gradient the weighted mean of theirs. Both are exact for any affine motion of the
particles, so a rigid or uniformly stretched body carries its Gaussians exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree
from torch import Tensor

from physgm.gaussians import Gaussians

# Largest voxel grid interior filling allocates (a bool each): 64 MB.
MAX_FILL_VOXELS = 2**26


@dataclass
class ParticleSample:
    """Rest particles chosen from Gaussians.

    Attributes:
        x: [P, 3] rest positions, m.
        volume: [P] rest volumes, m^3 (one voxel each).
        interior: [P] True for particles added by interior filling.
        spacing: voxel side, m.
    """

    x: Tensor  # [P, 3]
    volume: Tensor  # [P]
    interior: Tensor  # [P] bool
    spacing: float

    def __len__(self) -> int:
        return self.x.shape[0]


def _voxel_keys(points: np.ndarray, origin: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Integer voxel coordinates [N, 3] and their grid dims [3] (one voxel of padding each side)."""
    ijk = np.floor((points - origin) / spacing).astype(np.int64) + 1
    dims = ijk.max(0) + 2
    return ijk, dims


def voxel_downsample(
    points: np.ndarray,  # [N, 3] m
    spacing: float,  # voxel side, m
    origin: np.ndarray | None = None,  # [3] voxel grid corner, m; default: the points' minimum
) -> tuple[np.ndarray, np.ndarray]:
    """One point per occupied voxel at the centroid of the points in it.

    Returns:
        centroids [P, 3] and the occupied voxel coordinates [P, 3] (int, padded by one voxel).
    """
    if spacing <= 0:
        raise ValueError(f"voxel spacing must be positive, got {spacing}")
    origin = points.min(0) if origin is None else origin
    ijk, dims = _voxel_keys(points, origin, spacing)
    keys = np.ravel_multi_index(ijk.T, dims)
    uniq, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    sums = np.zeros((len(uniq), 3))
    np.add.at(sums, inverse, points)
    return sums / counts[:, None], np.stack(np.unravel_index(uniq, dims), -1)


def fill_interior(
    occupied: np.ndarray,  # [P, 3] int voxel coordinates of the surface (padded, >= 1)
    close_gaps: int = 1,  # morphological closing radius in voxels, seals pinholes in the shell
) -> np.ndarray:
    """Voxels enclosed by the occupied shell (flood fill from outside), [Q, 3] int, disjoint from it."""
    dims = occupied.max(0) + 2 + 2 * close_gaps
    if int(np.prod(dims)) > MAX_FILL_VOXELS:
        raise ValueError(
            f"interior filling needs a {dims.tolist()} voxel grid (> {MAX_FILL_VOXELS} voxels): the "
            "Gaussians span far more than the object; prune floaters (raise min_opacity) or set "
            "fill_interior: false"
        )
    grid = np.zeros(dims, dtype=bool)
    shift = occupied + close_gaps
    grid[tuple(shift.T)] = True
    shell = (
        ndimage.binary_closing(grid, structure=np.ones((3, 3, 3), bool), iterations=close_gaps)
        if close_gaps
        else grid
    )
    # Voxels the closing adds on the outside (staircase corners) are not inside; sealed pinholes
    # are left out too, their Gaussians' own voxels already hold particles.
    inside = ndimage.binary_fill_holes(shell) & ~shell
    return np.argwhere(inside) - close_gaps


def sample_particles(
    gaussians: Gaussians,
    spacing: float,  # particle spacing (voxel side), m
    min_opacity: float = 0.05,  # Gaussians fainter than this carry no mass
    fill: bool = True,  # fill the inside of closed shells
) -> ParticleSample:
    """Particles for the simulator from the Gaussians' centres (see module docstring)."""
    keep = gaussians.opacities >= min_opacity
    if int(keep.sum()) == 0:
        raise ValueError(
            f"no Gaussian has opacity >= {min_opacity}; lower min_opacity or check that the opacities are "
            "in [0, 1], not logits"
        )
    pts = gaussians.means[keep].detach().double().cpu().numpy()
    origin = pts.min(0)
    centroids, occupied = voxel_downsample(pts, spacing, origin)
    inner = fill_interior(occupied) if fill else np.zeros((0, 3), dtype=np.int64)
    # Voxel (i, j, k) spans origin + (ijk - 1) * spacing .. + spacing (one voxel of padding).
    inner_x = origin + (inner - 1 + 0.5) * spacing
    x = np.concatenate([centroids, inner_x])
    interior = np.concatenate([np.zeros(len(centroids), bool), np.ones(len(inner_x), bool)])
    device = gaussians.means.device
    return ParticleSample(
        x=torch.from_numpy(x).float().to(device),
        volume=torch.full((len(x),), spacing**3, device=device),
        interior=torch.from_numpy(interior).to(device),
        spacing=spacing,
    )


@dataclass
class Followers:
    """Each Gaussian's K nearest particles and weights.

    Attributes:
        index: [N, K] particle indices.
        weight: [N, K] normalised weights (sum 1 per row).
        offset: [N, K, 3] rest offsets X_g - X_j, m.
    """

    index: Tensor  # [N, K]
    weight: Tensor  # [N, K]
    offset: Tensor  # [N, K, 3]

    def apply(
        self,
        x: Tensor,  # [P, 3] particle positions, m
        F: Tensor | None = None,  # [P, 3, 3] particle deformation gradients; None: translation only
    ) -> tuple[Tensor, Tensor | None]:
        """Gaussian centres [N, 3] and deformation gradients [N, 3, 3] (None if F is None)."""
        x = x.to(self.weight)
        xj = x[self.index]  # [N, K, 3]
        if F is None:
            return (self.weight[..., None] * (xj + self.offset)).sum(1), None
        Fj = F.to(self.weight)[self.index]  # [N, K, 3, 3]
        moved = xj + (Fj @ self.offset[..., None])[..., 0]
        means = (self.weight[..., None] * moved).sum(1)
        return means, (self.weight[..., None, None] * Fj).sum(1)


def build_followers(
    means: Tensor,  # [N, 3] rest Gaussian centres, m
    particles: Tensor,  # [P, 3] rest particle positions, m
    k: int = 8,
    radius: float | None = None,  # kernel width, m; default: median distance to the nearest particle x 2
) -> Followers:
    """K nearest particles per Gaussian with Gaussian-kernel weights exp(-d^2 / (2 radius^2))."""
    p = particles.detach().double().cpu().numpy()
    q = means.detach().double().cpu().numpy()
    k = min(k, len(p))
    dist, idx = cKDTree(p).query(q, k=k)
    dist, idx = dist.reshape(len(q), k), idx.reshape(len(q), k)
    if radius is None:
        radius = max(2.0 * float(np.median(dist[:, 0])), 1e-9)
    # Relative to the nearest particle so far-away Gaussians (floaters) still get finite weights.
    logw = -(dist**2 - dist[:, :1] ** 2) / (2 * radius**2)
    w = np.exp(logw)
    w /= w.sum(1, keepdims=True)
    device = means.device
    offset = q[:, None, :] - p[idx]
    return Followers(
        index=torch.from_numpy(idx).long().to(device),
        weight=torch.from_numpy(w).float().to(device),
        offset=torch.from_numpy(offset).float().to(device),
    )
