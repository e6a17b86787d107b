"""Simulation particles from Gaussians, and Gaussians that follow the particles.

A reconstruction holds Gaussians packed on the surface and nothing inside a hollow shell, while MPM
needs its particles spread through the volume at a steady density: about 8 per grid cell (2 per
axis) is the usual practice, and at 0.3-1 per cell a soft body loses its shape (issue 24: a 20 cm
jelly cube sampled at the surface sank to 55 % of its height). So, like PhysGaussian's particle
filling, we (1) drop near-transparent Gaussians (``mass_opacity`` picks the threshold), (2)
voxelise what is left on a lattice of side ``spacing`` (the particle spacing, dx / 2 at the
planner's default) that exactly spans the Gaussians' bounding box: a voxel is occupied when a
Gaussian's centre or a corner of its sigma box (at most a voxel away) lies in it, (3) fill the
voxels the occupied shell encloses (a flood fill from outside after a morphological closing seals
pinholes, or PhysGaussian's test that rays along all 6 axis directions meet the shell, which also
fills leaky shells; O(voxels), with the voxel count capped), and (4) put one particle at the centre
of every enclosed voxel and of every shell voxel whose centre lies on the inner side of the surface
through it, each carrying the volume spacing^3. The interior of a closed surface is thus filled at
the same density as its skin; an open sheet stays a sheet. Every Gaussian then follows its K
nearest particles: its centre is the weighted first-order extrapolation of the particles' motion,
x_g = sum_j w_j (x_j + F_j (X_g - X_j)), and its deformation gradient the weighted mean of theirs.
Both are exact for any affine motion of the particles, so a rigid or uniformly stretched body
carries its Gaussians exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree
from torch import Tensor

from physgm.gaussians import Gaussians, quat_to_rotmat

# Largest voxel grid interior filling allocates (a bool each): 64 MB.
MAX_FILL_VOXELS = 2**26
# Points of each Gaussian that mark voxels, in units of its principal sigmas: the 3 x 3 x 3 box
# {-1, 0, 1}^3, so splats wider than a voxel also mark the voxels next to their centre. [27, 3]
_BOX_POINTS = torch.cartesian_prod(*[torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float64)] * 3)
_CHUNK = 65_536  # Gaussians voxelised at once (27 points each: ~40 MB of float64)
_DENSE_VOXELS = 1 << 21  # lattices up to this many voxels are tallied densely (64 MB of float64)
MASS_QUANTILE = 0.99  # an object's strong opacity, for ``mass_opacity``: its Gaussians' 99th percentile
MASS_OPACITY_FLOOR = 0.005  # ``mass_opacity`` never goes below this: fainter Gaussians carry no mass


@dataclass
class ParticleSample:
    """Rest particles chosen from Gaussians.

    Attributes:
        x: [P, 3] rest positions, m (voxel centres of a regular lattice).
        volume: [P] rest volumes, m^3 (one voxel each).
        interior: [P] True for particles in voxels no Gaussian touches (added by filling).
        spacing: voxel side (particle spacing), m; ``split_along`` puts n particles a voxel
            along one axis.
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


def _hit_on_every_axis(solid: np.ndarray) -> np.ndarray:
    """[X, Y, Z] bool: voxels with a solid voxel somewhere along each of the 6 axis directions."""
    hit = np.ones_like(solid)
    for axis in range(3):
        forward = np.logical_or.accumulate(solid, axis=axis)
        backward = np.flip(np.logical_or.accumulate(np.flip(solid, axis), axis=axis), axis)
        hit &= forward & backward
    return hit


def fill_interior(
    occupied: np.ndarray,  # [P, 3] int voxel coordinates of the surface (padded, >= 1)
    close_gaps: int = 1,  # morphological closing radius in voxels, seals pinholes in the shell
) -> np.ndarray:
    """Voxels the occupied shell encloses, [Q, 3] int, disjoint from it.

    A voxel is inside if a flood fill from outside cannot reach it once pinholes are closed, or
    if a ray along each of the 6 axis directions meets the shell (PhysGaussian's test). The second
    fills leaky shells, which reconstructions from few views produce: the tiny model's cloud for
    examples/jelly_cube.png encloses nothing by flood fill. It leaves open shapes (a sheet, a bowl
    seen from its open side) empty. Both are O(voxels); the voxel count is capped.
    """
    dims = occupied.max(0) + 2 + 2 * close_gaps
    if int(np.prod(dims)) > MAX_FILL_VOXELS:
        raise ValueError(
            f"interior filling needs a {dims.tolist()} voxel grid (> {MAX_FILL_VOXELS} voxels): the "
            f"Gaussians span "
            "far more than the object; prune floaters (raise min_opacity) or set fill_interior: false"
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
    # are left out too: the closing only bridges gaps narrower than the surface's own voxels.
    inside = (ndimage.binary_fill_holes(shell) & ~shell) | (_hit_on_every_axis(grid) & ~grid)
    return np.argwhere(inside) - close_gaps


def lattice_frame(
    lo: np.ndarray,  # [3] bounding-box corner, m
    hi: np.ndarray,  # [3] m
    spacing: float,  # voxel side, m
) -> tuple[np.ndarray, np.ndarray]:
    """(origin [3] m, voxel counts [3]) of the lattice that spans [lo, hi], centred on it.

    ceil(extent / spacing) voxels per axis (at least one), so a box of whole voxels is covered
    exactly and any other overhangs by under half a voxel on each side.
    """
    if not spacing > 0:
        raise ValueError(f"voxel spacing must be positive, got {spacing}")
    n = np.maximum(np.ceil((hi - lo) / spacing - 1e-6), 1).astype(np.int64)
    return 0.5 * (lo + hi) - 0.5 * n * spacing, n


def occupied_voxels(
    gaussians: Gaussians,  # the opaque Gaussians only
    origin: np.ndarray,  # [3] lattice corner, m
    counts: np.ndarray,  # [3] voxels per axis
    spacing: float,  # voxel side, m
) -> tuple[np.ndarray, np.ndarray]:
    """Voxels touched by a Gaussian's centre or its sigma box (clipped to one voxel each way).

    Returns:
        voxels [Q, 3] (int, unpadded, unique) and the centroid [Q, 3] (m) of the marking points in
        each: where the surface passes through the voxel.
    """
    # A lattice this small is tallied in dense arrays, without sorting; a larger one (a few far
    # floaters span it) by the voxels each chunk touches. Both add each voxel's points in the
    # same order, so they give the same sums.
    volume = int(np.prod(counts))
    dense = volume <= _DENSE_VOXELS
    c, acc = (np.zeros(volume), np.zeros((volume, 3))) if dense else (None, None)
    keys, sums, n = [], [], []
    for start in range(0, len(gaussians), _CHUNK):
        part = gaussians[start : start + _CHUNK]
        means = part.means.detach().double().cpu()
        rot = quat_to_rotmat(part.quats.detach().double().cpu())
        # Columns: the principal sigma axes, shortened to one voxel so that the 3 x 3 x 3 points
        # leave no voxel out between them and a floater or huge splat cannot flood the box.
        axes = rot * part.scales.detach().double().cpu().clamp_max(spacing)[:, None, :]
        pts = (means[:, None, :] + _BOX_POINTS @ axes.transpose(1, 2)).reshape(-1, 3).numpy()  # [n * 27, 3]
        ijk = np.clip(np.floor((pts - origin) / spacing).astype(np.int64), 0, counts - 1)
        flat = np.ravel_multi_index(ijk.T, counts)
        if dense:
            c += np.bincount(flat, minlength=volume)
            for a in range(3):
                acc[:, a] += np.bincount(flat, pts[:, a], volume)
            continue
        k, inverse = np.unique(flat, return_inverse=True)
        keys.append(k), n.append(np.bincount(inverse, minlength=len(k)))
        sums.append(np.stack([np.bincount(inverse, pts[:, a], len(k)) for a in range(3)], -1))
    if dense:
        k = np.flatnonzero(c)
        c, acc = c[k], acc[k]
    else:
        k, inverse = np.unique(np.concatenate(keys), return_inverse=True)
        c = np.bincount(inverse, np.concatenate(n), len(k))
        acc = np.stack([np.bincount(inverse, np.concatenate(sums)[:, a], len(k)) for a in range(3)], -1)
    return np.stack(np.unravel_index(k, counts), -1), acc / c[:, None]


def _inner_side(
    shell: np.ndarray,  # [Q, 3] int shell voxels (unpadded)
    surface: np.ndarray,  # [Q, 3] m, where the surface crosses each
    inner: np.ndarray,  # [R, 3] int enclosed voxels (unpadded)
    origin: np.ndarray,  # [3] m
    counts: np.ndarray,  # [3]
    spacing: float,  # m
) -> np.ndarray:
    """[Q] bool: keep the shell voxel's particle (its centre is not outside the surface)?

    A whole particle per shell voxel would thicken the body by about half a voxel all round (a
    sphere of radius 10 voxels came out 26 % too heavy). Only shell voxels next to the outside
    are tested (a thick, volumetric cloud keeps its deeper voxels): the outward normal is minus
    the gradient of the smoothed solid mask, and a voxel whose centre lies beyond the surface
    point along it is dropped. Without a normal (an open sheet, a thin part) the particle stays.
    """
    solid = np.zeros(counts + 2, dtype=bool)  # one voxel of padding
    solid[tuple((inner + 1).T)] = True
    has_inner = solid.copy()
    solid[tuple((shell + 1).T)] = True
    near_outside = ndimage.binary_dilation(~solid, np.ones((3, 3, 3), bool))
    outside_near = near_outside[tuple((shell + 1).T)]  # [Q] shell voxels on the body's face
    smooth = ndimage.gaussian_filter(has_inner.astype(np.float64), sigma=1.0, mode="constant")
    grads = np.stack(np.gradient(smooth), -1)[tuple((shell + 1).T)]  # [Q, 3] points inwards
    centre = origin + (shell + 0.5) * spacing
    return ~outside_near | (np.einsum("qi,qi->q", centre - surface, grads) >= 0.0)


def mass_opacity(
    opacities: Tensor,  # [N] the object's Gaussians' opacities
    min_opacity: float,  # the threshold for an opaque object
    relative: float,  # share of the object's strong opacity (99th percentile); 0: min_opacity alone
) -> float:
    """Opacity from which a Gaussian carries mass: ``min_opacity``, or ``relative`` times the 99th
    percentile of ``opacities`` when that is lower, but never below ``MASS_OPACITY_FLOOR``.

    Opacity says how much light a Gaussian blocks, not whether there is matter behind it. A
    translucent object (jelly, glass) is drawn with faint Gaussians throughout, and a fixed 0.05
    kept a third of its body (docs/model.md, "How much body a translucent object gets"); scaled to
    the object's own strongest Gaussians, the threshold keeps an opaque object's and finds a
    translucent one's.
    """
    if relative <= 0.0 or opacities.numel() == 0:
        return min_opacity
    # numpy: torch.quantile refuses more than 16M values, and a 3DGS scene can hold them
    strong = float(np.quantile(opacities.detach().float().cpu().numpy(), MASS_QUANTILE))
    return min(min_opacity, max(relative * strong, MASS_OPACITY_FLOOR))


def sample_particles(
    gaussians: Gaussians,
    spacing: float,  # particle spacing (voxel side), m
    min_opacity: float = 0.05,  # Gaussians fainter than this carry no mass
    fill: bool = True,  # fill the inside of closed shells
) -> ParticleSample:
    """Particles on a regular lattice through the volume the Gaussians enclose (see module docstring)."""
    keep = gaussians.opacities >= min_opacity
    if int(keep.sum()) == 0:
        raise ValueError(
            f"no Gaussian has opacity >= {min_opacity}; lower min_opacity or check that the opacities "
            f"are in [0, 1], not logits"
        )
    opaque = gaussians[keep]
    pts = opaque.means.detach().double().cpu().numpy()
    origin, counts = lattice_frame(pts.min(0), pts.max(0), spacing)
    shell, surface = occupied_voxels(opaque, origin, counts, spacing)
    inner = np.zeros((0, 3), dtype=np.int64)
    if fill:  # fill_interior works on padded coordinates (>= 1); its own grid adds the closing margin
        inner = fill_interior(shell + 1) - 1
        shell = shell[_inner_side(shell, surface, inner, origin, counts, spacing)]
    voxels = np.concatenate([shell, inner])
    x = origin + (voxels + 0.5) * spacing
    interior = np.concatenate([np.zeros(len(shell), bool), np.ones(len(inner), bool)])
    device = gaussians.means.device
    return ParticleSample(
        x=torch.from_numpy(x).float().to(device),
        volume=torch.full((len(x),), spacing**3, device=device),
        interior=torch.from_numpy(interior).to(device),
        spacing=spacing,
    )


def split_along(sample: ParticleSample, axis: int, n: int) -> ParticleSample:
    """Each particle's voxel cut into ``n`` slabs along ``axis``, one particle at each slab's centre.

    For a body a scene stretches along ``axis`` (``planner.stretch_splits``): the particles along
    it start ``spacing / n`` apart and the sample's mass is unchanged.
    """
    if n < 1:
        raise ValueError(f"need n >= 1 slabs per voxel, got {n}")
    if n == 1:
        return sample
    offsets = torch.zeros(n, 3, dtype=sample.x.dtype, device=sample.x.device)  # [n, 3]
    offsets[:, axis] = ((torch.arange(n, device=sample.x.device) + 0.5) / n - 0.5) * sample.spacing
    return ParticleSample(
        x=(sample.x[:, None, :] + offsets).reshape(-1, 3),
        volume=(sample.volume / n).repeat_interleave(n),
        interior=sample.interior.repeat_interleave(n),
        spacing=sample.spacing,
    )


@dataclass
class Followers:
    """Each Gaussian's K nearest particles and weights.

    Attributes:
        index: [N, K] particle indices (int32: a capture's millions of Gaussians hold 8 each).
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
    dist, idx = cKDTree(p).query(q, k=k, workers=2)  # the same answer, the query on two threads
    dist, idx = dist.reshape(len(q), k), idx.reshape(len(q), k)
    if radius is None:
        radius = max(2.0 * float(np.median(dist[:, 0])), 1e-9)
    # Relative to the nearest particle so far-away Gaussians (floaters) still get finite weights.
    logw = -(dist**2 - dist[:, :1] ** 2) / (2 * radius**2)
    w = np.exp(logw)
    w /= w.sum(1, keepdims=True)
    index = torch.from_numpy(idx).int().to(means.device)
    # In the inputs' own precision: a float32 difference is the float64 one rounded to float32,
    # the same bits at half the memory (a capture's millions of Gaussians hold 8 offsets each).
    rest = means.detach()
    offset = rest[:, None, :] - particles.detach().to(rest)[index]
    return Followers(
        index=index,
        weight=torch.from_numpy(w).float().to(means.device),
        offset=offset.float(),
    )
