"""Particle selection from Gaussians (pruning, voxel downsampling, interior filling) and followers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from physgm.gaussians import Gaussians, quat_to_rotmat
from physgm.sim.sampling import (
    ParticleSample,
    build_followers,
    fill_interior,
    lattice_frame,
    mass_opacity,
    occupied_voxels,
    sample_particles,
    split_along,
    voxel_downsample,
)


def _gaussians(means: torch.Tensor, opacities: torch.Tensor | None = None) -> Gaussians:
    n = means.shape[0]
    return Gaussians(
        means=means,
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        scales=torch.full((n, 3), 0.002),
        opacities=torch.ones(n) if opacities is None else opacities,
        colors=torch.rand(n, 3),
    )


def _sphere_shell(n: int, radius: float, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * radius


def test_voxel_downsample_counts_occupied_voxels_and_averages():
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.03, 0.03], [0.15, 0.01, 0.01], [0.16, 0.02, 0.02]])
    centroids, voxels = voxel_downsample(pts, spacing=0.1, origin=np.zeros(3))
    assert len(centroids) == 2
    np.testing.assert_allclose(sorted(centroids[:, 0]), [0.02, 0.155])
    # A dense uniform cloud: one particle per voxel of the box it fills.
    rng = np.random.default_rng(0)
    dense = rng.uniform(0, 0.2, (50000, 3))
    centroids, _ = voxel_downsample(dense, spacing=0.02, origin=np.zeros(3))
    assert len(centroids) == 10**3


def test_opacity_pruning_drops_faint_gaussians():
    means = torch.cat([torch.rand(1000, 3) * 0.1, torch.rand(1000, 3) * 0.1 + 1.0])
    opac = torch.cat([torch.full((1000,), 0.9), torch.full((1000,), 0.01)])
    sample = sample_particles(_gaussians(means, opac), spacing=0.01, fill=False)
    assert sample.x.max() < 0.11  # nothing near the faint cloud at (1, 1, 1)
    with pytest.raises(ValueError, match="opacity"):
        sample_particles(_gaussians(means, torch.zeros(2000)), spacing=0.01)


def test_interior_filling_fills_a_hollow_sphere():
    radius, spacing = 0.1, 0.01
    shell = _gaussians(_sphere_shell(20000, radius))
    hollow = sample_particles(shell, spacing, fill=False)
    filled = sample_particles(shell, spacing, fill=True)
    r = filled.x.norm(dim=-1)
    inner = r[filled.interior]
    # The inside is filled down to the centre, and only the inside.
    assert inner.min() < 1.5 * spacing and inner.max() < radius
    # Shell voxels keep their particle only on the inner side of the surface: the volume is right.
    assert float(filled.volume.sum()) == pytest.approx(4 / 3 * math.pi * radius**3, rel=0.03)
    assert float(r.max()) < radius
    # Every interior voxel centre within the sphere, one voxel away from the shell, is present.
    g = torch.arange(-radius, radius, spacing) + spacing / 2
    lattice = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    deep = lattice[lattice.norm(dim=-1) < radius - 2 * spacing]
    dist = torch.cdist(deep, filled.x).min(dim=1).values
    assert dist.max() < 0.75 * spacing
    assert not hollow.interior.any() and len(hollow) >= int((~filled.interior).sum())


def test_fill_interior_ignores_open_shapes():
    # A flat square sheet encloses nothing.
    ij = np.stack(np.meshgrid(np.arange(1, 11), np.arange(1, 11), indexing="ij"), -1).reshape(-1, 2)
    sheet = np.concatenate([ij, np.full((len(ij), 1), 3)], 1)
    assert len(fill_interior(sheet)) == 0


def test_followers_move_rigidly_with_rigid_particle_motion():
    shell = _gaussians(_sphere_shell(5000, 0.1, seed=1))
    sample = sample_particles(shell, 0.015)
    followers = build_followers(shell.means, sample.x, k=8)
    rot = quat_to_rotmat(torch.nn.functional.normalize(torch.tensor([0.3, -0.2, 0.9, 0.1]), dim=0))
    shift = torch.tensor([0.2, -0.5, 1.0])
    means, F = followers.apply(sample.x @ rot.T + shift, rot.expand(len(sample), 3, 3))
    torch.testing.assert_close(means, shell.means @ rot.T + shift, atol=2e-6, rtol=0)
    torch.testing.assert_close(F, rot.expand(len(shell), 3, 3), atol=1e-6, rtol=0)
    torch.testing.assert_close(followers.weight.sum(1), torch.ones(len(shell)))


def test_followers_exact_for_affine_motion_and_smooth_for_nonaffine():
    shell = _gaussians(_sphere_shell(3000, 0.1, seed=2))
    sample = sample_particles(shell, 0.015)
    followers = build_followers(shell.means, sample.x, k=8)
    A = torch.tensor([[1.2, 0.1, 0.0], [0.0, 0.9, 0.2], [0.05, 0.0, 1.1]])
    means, _ = followers.apply(sample.x @ A.T, A.expand(len(sample), 3, 3))
    torch.testing.assert_close(means, shell.means @ A.T, atol=2e-6, rtol=0)

    # A bend x += 0.5 z^2 e_x: with the particles' F the error is second order in the spacing,
    # and clearly below the translation-only interpolation.
    def bend(p: torch.Tensor) -> torch.Tensor:
        zero = torch.zeros_like(p[:, 0])
        return p + 0.5 * torch.stack([p[:, 2] ** 2, zero, zero], -1)

    grad = torch.eye(3).repeat(len(sample), 1, 1)
    grad[:, 0, 2] = sample.x[:, 2]
    err_f = (followers.apply(bend(sample.x), grad)[0] - bend(shell.means)).norm(dim=-1).max()
    err_t = (followers.apply(bend(sample.x))[0] - bend(shell.means)).norm(dim=-1).max()
    # 0.5 d^2 with a lattice neighbour up to d = sqrt(2) spacings from the Gaussian (1.2e-4 measured).
    assert err_f < 0.015**2 and err_f < 0.2 * err_t


def test_interior_filling_refuses_a_huge_grid_from_floaters():
    means = torch.cat([_sphere_shell(2000, 0.1), torch.tensor([[50.0, 50.0, 50.0]])])
    with pytest.raises(ValueError, match="floaters"):
        sample_particles(_gaussians(means), spacing=0.01, fill=True)


def _cube_shell(n: int, side: float, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    face = torch.randint(0, 6, (n,), generator=g)
    pts = (torch.rand(n, 3, generator=g) - 0.5) * side
    pts[torch.arange(n), face // 2] = side * ((face % 2) - 0.5)
    return pts


def test_hollow_cube_becomes_a_full_lattice_at_the_requested_density():
    # 24 voxels across: exactly 24^3 particles at the voxel centres, i.e. 8 per cell of dx = 2 spacing.
    side, spacing = 0.2, 0.2 / 24
    sample = sample_particles(_gaussians(_cube_shell(30000, side)), spacing)
    assert len(sample) == 24**3
    assert float(sample.volume.sum()) == pytest.approx(side**3, rel=1e-5)
    lo, hi = sample.x.min(0).values, sample.x.max(0).values
    torch.testing.assert_close(lo, torch.full((3,), -side / 2 + spacing / 2), atol=1e-6, rtol=0)
    torch.testing.assert_close(hi, torch.full((3,), side / 2 - spacing / 2), atol=1e-6, rtol=0)
    # Regular lattice: every particle's nearest neighbour is one spacing away.
    nearest = torch.cdist(sample.x, sample.x).fill_diagonal_(1.0).min(1).values
    torch.testing.assert_close(nearest, torch.full_like(nearest, spacing), atol=1e-6, rtol=0)


def test_mass_opacity_keeps_an_opaque_object_and_scales_to_a_translucent_one():
    g = torch.Generator().manual_seed(0)
    opaque = torch.cat([torch.rand(9000, generator=g) * 0.01, 0.3 + 0.6 * torch.rand(1000, generator=g)])
    assert mass_opacity(opaque, 0.05, 0.25) == 0.05  # its strong Gaussians reach 0.3-0.9
    faint = 0.04 * torch.rand(10000, generator=g)  # a jelly drawn at opacities up to 0.04
    q99 = float(torch.quantile(faint, 0.99))
    assert mass_opacity(faint, 0.05, 0.25) == pytest.approx(0.25 * q99)
    assert mass_opacity(faint, 0.05, 0.0) == 0.05  # relative 0: the fixed threshold
    assert mass_opacity(torch.zeros(100), 0.05, 0.25) == 0.005  # never below the floor
    assert mass_opacity(faint, 0.003, 0.25) == 0.003  # nor above min_opacity


def test_a_translucent_cube_gets_its_whole_body_at_the_mass_opacity():
    # A 20 cm cube drawn with faint Gaussians (opacity 0.01-0.04, as the model draws jelly): at the
    # fixed 0.05 nothing carries mass; at mass_opacity the shell fills to the cube's volume.
    side, spacing = 0.2, 0.2 / 12
    g = torch.Generator().manual_seed(1)
    cube = _gaussians(_cube_shell(20000, side), 0.01 + 0.03 * torch.rand(20000, generator=g))
    with pytest.raises(ValueError, match="opacity"):
        sample_particles(cube, spacing, min_opacity=0.05)
    sample = sample_particles(cube, spacing, min_opacity=mass_opacity(cube.opacities, 0.05, 0.25))
    assert float(sample.volume.sum()) == pytest.approx(side**3, rel=0.02)


def test_lattice_frame_spans_the_box_centred():
    origin, counts = lattice_frame(np.zeros(3), np.array([0.1, 0.105, 0.0]), 0.01)
    assert counts.tolist() == [10, 11, 1]
    np.testing.assert_allclose(origin, [0.0, -0.0025, -0.005])


def test_leaky_shell_is_filled_and_a_sheet_stays_a_sheet():
    # A sphere shell too sparse to close (2000 points on ~1600 surface voxels leave holes): a
    # flood fill leaks and fills nothing, the 6-ray test still fills most of it (86 % measured).
    radius, spacing = 0.1, 0.01
    sparse = _gaussians(_sphere_shell(2000, radius, seed=3))
    sample = sample_particles(sparse, spacing)
    assert float(sample.volume.sum()) == pytest.approx(4 / 3 * math.pi * radius**3, rel=0.2)
    g = torch.Generator().manual_seed(4)
    sheet = torch.cat([torch.rand(5000, 2, generator=g) * 0.2, torch.zeros(5000, 1)], 1)
    flat = sample_particles(_gaussians(sheet), spacing)
    assert not flat.interior.any() and float(flat.x[:, 2].abs().max()) <= spacing / 2 + 1e-6


def test_wide_splats_mark_the_voxels_they_cover():
    # Flat Gaussians 1.5 voxels wide on every other voxel of a plane: their centres alone mark a
    # quarter of the plane's voxels, their sigma boxes all of them.
    spacing = 0.01
    ij = torch.stack(torch.meshgrid(torch.arange(10), torch.arange(10), indexing="ij"), -1).reshape(-1, 2)
    xy = torch.cat([ij * 0.02, torch.tensor([[0.185, 0.185]])]).float()  # 19 voxels across, off the faces
    g = _gaussians(torch.cat([xy, torch.zeros(len(xy), 1)], 1))
    g.scales = torch.tensor([[0.015, 0.015, 1e-4]]).repeat(len(xy), 1)
    assert len(sample_particles(g, spacing, fill=False)) == 19 * 19
    g.scales = torch.full((len(xy), 3), 1e-4)
    # The extra Gaussian shares the voxel of (0.18, 0.18).
    assert len(sample_particles(g, spacing, fill=False)) == 100


def test_split_along_cuts_each_voxel_into_slabs():
    sample = ParticleSample(
        x=torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]),
        volume=torch.full((2,), 1e-3),
        interior=torch.tensor([True, False]),
        spacing=0.1,
    )
    split = split_along(sample, axis=2, n=4)
    assert len(split) == 8 and split.spacing == 0.1
    torch.testing.assert_close(split.x[:4, 2], torch.tensor([-0.0375, -0.0125, 0.0125, 0.0375]))
    torch.testing.assert_close(split.x[:4, :2], torch.zeros(4, 2))
    assert float(split.volume.sum()) == pytest.approx(2e-3)
    assert split.interior.tolist() == [True] * 4 + [False] * 4
    assert split_along(sample, 0, 1) is sample
    with pytest.raises(ValueError, match="n >= 1"):
        split_along(sample, 0, 0)


def test_dense_and_sparse_voxel_tallies_agree_to_the_bit(monkeypatch):
    """A small lattice is tallied in dense arrays, a large one by sorting; both give the same
    voxels and surface points (more Gaussians than one chunk, so chunks are summed too)."""
    from physgm.sim import sampling

    n = sampling._CHUNK + 5000
    g = torch.Generator().manual_seed(3)
    gs = Gaussians(
        means=torch.rand(n, 3, generator=g) * torch.tensor([0.3, 0.2, 0.1]),
        quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
        scales=torch.rand(n, 3, generator=g) * 0.01,
        opacities=torch.ones(n),
        colors=torch.rand(n, 3, generator=g),
    )
    origin, counts = lattice_frame(np.zeros(3), np.array([0.3, 0.2, 0.1]), 0.01)
    dense = occupied_voxels(gs, origin, counts, 0.01)
    monkeypatch.setattr(sampling, "_DENSE_VOXELS", 0)
    sparse = occupied_voxels(gs, origin, counts, 0.01)
    assert len(dense[0]) > 1000
    np.testing.assert_array_equal(dense[0], sparse[0])
    np.testing.assert_array_equal(dense[1], sparse[1])
