"""Gaussian coupling: covariances follow F, quats/scales reproduce F Sigma F^T."""

from __future__ import annotations

import math

import torch

from physgm.gaussians import Gaussians, quat_to_rotmat, rotmat_to_quat
from physgm.sim.coupling import (
    covariance_to_quat_scale,
    deform_covariances,
    deform_gaussians,
    quat_multiply,
    rigid_transform_gaussians,
)


def _random_gaussians(n: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    # Distinct scales per axis so the eigen decomposition is unique up to sign.
    scales = torch.stack([torch.full((n,), 0.01), torch.full((n,), 0.02), torch.full((n,), 0.04)], -1)
    scales = scales * (1 + 0.2 * torch.rand(n, 1, generator=g))
    return Gaussians(
        means=torch.randn(n, 3, generator=g),
        quats=quats,
        scales=scales,
        opacities=torch.rand(n, generator=g),
        colors=torch.rand(n, 3, generator=g),
    )


def _random_rotations(n: int, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return quat_to_rotmat(torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1))


def _same_quat(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Quaternion distance up to the q ~ -q ambiguity, [N]."""
    return torch.minimum((a - b).norm(dim=-1), (a + b).norm(dim=-1))


def test_rotation_F_rotates_gaussians_exactly():
    gs = _random_gaussians(500)
    rot = _random_rotations(500)
    out = deform_gaussians(gs, gs.means, rot)
    torch.testing.assert_close(out.scales, gs.scales, atol=1e-6, rtol=1e-5)
    expected = quat_multiply(rotmat_to_quat(rot), gs.quats)
    assert _same_quat(out.quats, expected).max() < 1e-4


def test_diagonal_stretch_scales_axis_aligned_gaussians():
    n = 64
    gs = _random_gaussians(n)
    gs.quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1)
    stretch = torch.tensor([1.5, 0.7, 1.2])
    out = deform_gaussians(gs, gs.means, torch.diag(stretch).expand(n, 3, 3))
    torch.testing.assert_close(out.scales, gs.scales * stretch, rtol=1e-5, atol=1e-7)
    assert _same_quat(out.quats, gs.quats).max() < 1e-5


def test_random_F_reconstructs_deformed_covariance():
    gs = _random_gaussians(2000, seed=3)
    g = torch.Generator().manual_seed(4)
    F = torch.eye(3) + 0.4 * torch.randn(2000, 3, 3, generator=g)
    F = torch.where(torch.linalg.det(F)[:, None, None] < 0, -F, F)  # keep det > 0 like physical F
    out = deform_gaussians(gs, gs.means, F)
    expected = deform_covariances(gs.covariances().double(), F.double())
    rel = (out.covariances().double() - expected).norm(dim=(-2, -1)) / expected.norm(dim=(-2, -1))
    assert rel.max() < 1e-5
    # Unit quaternions, positive scales.
    torch.testing.assert_close(out.quats.norm(dim=-1), torch.ones(2000), atol=1e-6, rtol=0)
    assert (out.scales > 0).all()


def test_axis_labels_stay_continuous_under_small_deformation():
    # A small shear must not swap the axes: each scale changes by a small amount.
    gs = _random_gaussians(300, seed=5)
    F = torch.eye(3) + 0.05 * torch.randn(300, 3, 3, generator=torch.Generator().manual_seed(6))
    out = deform_gaussians(gs, gs.means, F)
    assert ((out.scales / gs.scales) - 1).abs().max() < 0.25
    # Rotation of each axis is small: R_t^T R_0 close to identity.
    rel = quat_to_rotmat(out.quats).transpose(-1, -2) @ quat_to_rotmat(gs.quats)
    angle = torch.arccos(((rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1))
    assert angle.max() < math.radians(25)


def test_covariance_to_quat_scale_without_reference_is_sorted():
    covs = torch.diag(torch.tensor([9.0, 1.0, 4.0]))[None]
    quats, scales = covariance_to_quat_scale(covs)
    torch.testing.assert_close(scales[0], torch.tensor([1.0, 2.0, 3.0]))
    rot = quat_to_rotmat(quats)
    torch.testing.assert_close(
        rot @ torch.diag_embed(scales**2) @ rot.transpose(-1, -2), covs, atol=1e-5, rtol=1e-5
    )


def test_rigid_transform_matches_deform_with_rotation():
    gs = _random_gaussians(200, seed=7)
    rot = _random_rotations(1, seed=8)[0]
    center = torch.tensor([0.1, -0.2, 0.3])
    shift = torch.tensor([0.5, 0.0, -1.0])
    out = rigid_transform_gaussians(gs, rot, shift, center)
    means = (gs.means - center) @ rot.T + center + shift
    ref = deform_gaussians(gs, means, rot.expand(200, 3, 3))
    torch.testing.assert_close(out.means, ref.means)
    torch.testing.assert_close(out.covariances(), ref.covariances(), atol=1e-7, rtol=1e-4)
    torch.testing.assert_close(out.scales, gs.scales)


def _followed_scene(n: int, p: int, seed: int, k: int = 8):
    """n random Gaussians following p particles moved and deformed at random: (gaussians,
    followers, particles' rest positions, positions, deformation gradients)."""
    from physgm.sim.sampling import build_followers

    gs = _random_gaussians(n, seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    particles = torch.randn(p, 3, generator=g)
    followers = build_followers(gs.means, particles, k=k)
    x = particles + 0.05 * torch.randn(p, 3, generator=g)
    F = torch.eye(3) + 0.3 * torch.randn(p, 3, 3, generator=g)
    return gs, followers, particles, x, F


def test_warp_follow_and_deform_matches_torch_twin():
    from physgm.sim.coupling import follow_and_deform

    gs, followers, particles, x, F = _followed_scene(3000, 800, seed=11, k=6)
    F = torch.where(torch.linalg.det(F)[:, None, None] < 0, -F, F)
    fast = follow_and_deform(gs, followers, x, F)
    means, Fg = followers.apply(x, F)
    ref = deform_gaussians(gs, means, Fg)
    torch.testing.assert_close(fast.means, ref.means, atol=1e-5, rtol=1e-5)
    covs, ref_covs = fast.covariances().double(), ref.covariances().double()
    rel = (covs - ref_covs).norm(dim=(-2, -1)) / ref_covs.norm(dim=(-2, -1))
    assert rel.max() < 1e-4  # float32 eigen-solver in the kernel
    # Same axis labelling as the twin: scales agree axis by axis.
    torch.testing.assert_close(fast.scales, ref.scales, atol=1e-6, rtol=1e-3)
    torch.testing.assert_close(fast.quats.norm(dim=-1), torch.ones(3000), atol=1e-5, rtol=0)
    # Rest state (F = I, x = X): the Gaussians come back unchanged.
    same = follow_and_deform(gs, followers, particles, torch.eye(3).expand(800, 3, 3))
    torch.testing.assert_close(same.means, gs.means, atol=1e-5, rtol=0)
    torch.testing.assert_close(same.covariances(), gs.covariances(), atol=1e-8, rtol=1e-4)


def test_warp_follow_covariances_matches_torch_twin():
    from physgm.sim.coupling import follow_covariances

    gs, followers, _, x, F = _followed_scene(2000, 500, seed=13)
    means, covs = follow_covariances(followers, gs.covariances(), x, F)
    ref_means, Fg = followers.apply(x, F)
    torch.testing.assert_close(means, ref_means, atol=1e-5, rtol=1e-5)
    ref_covs = deform_covariances(gs.covariances().double(), Fg.double())
    torch.testing.assert_close(covs.double(), ref_covs, atol=1e-9, rtol=1e-5)


def test_two_threads_deform_exactly_as_one():
    """Each thread takes a range of the Gaussians; every Gaussian is computed alone, so the split
    changes no bit."""
    from physgm.sim.coupling import PARALLEL_MIN_GAUSSIANS, follow_and_deform, follow_covariances

    # an odd count: the ranges differ in size
    gs, followers, _, x, F = _followed_scene(PARALLEL_MIN_GAUSSIANS + 1001, 700, seed=15)
    one, two = (follow_and_deform(gs, followers, x, F, num_threads=k) for k in (1, 2))
    for a, b in ((one.means, two.means), (one.quats, two.quats), (one.scales, two.scales)):
        assert torch.equal(a, b)
    one, two = (follow_covariances(followers, gs.covariances(), x, F, num_threads=k) for k in (1, 2))
    assert torch.equal(one[0], two[0]) and torch.equal(one[1], two[1])


def test_round_gaussians_turned_by_the_simulation_stay_round():
    """Round Gaussians of 1 cm carried by nearly rigid rotations (a body at rest after a bounce):
    their covariances, ~1e-4 m^2, have an eigen-split whose cross products would reach float32's
    denormals; the kernel must still give three equal scales (it gave 0.0097 for 0.0105 before)."""
    from physgm.sim.coupling import follow_and_deform
    from physgm.sim.sampling import build_followers

    n, p = 2000, 300
    g = torch.Generator().manual_seed(5)
    gs = Gaussians(
        means=torch.rand(n, 3, generator=g) * 0.2,
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        scales=torch.full((n, 3), 0.0105),
        opacities=torch.full((n,), 0.9),
        colors=torch.rand(n, 3, generator=g),
    )
    particles = torch.rand(p, 3, generator=g) * 0.2
    followers = build_followers(gs.means, particles)
    F = _random_rotations(1, seed=6).expand(p, 3, 3) + 1e-7 * torch.randn(p, 3, 3, generator=g)
    fast = follow_and_deform(gs, followers, particles, F)
    means, Fg = followers.apply(particles, F)
    ref = deform_gaussians(gs, means, Fg)
    torch.testing.assert_close(fast.scales, ref.scales, atol=0, rtol=1e-4)
    rel = (fast.covariances() - ref.covariances()).norm(dim=(-2, -1)) / ref.covariances().norm(dim=(-2, -1))
    assert rel.max() < 1e-4


def test_gaussians_from_a_3dgs_ply_deform_like_the_originals(tmp_path):
    from physgm.gaussians import read_ply, write_ply

    gs = _random_gaussians(400, seed=13)
    write_ply(gs, tmp_path / "object.ply")
    loaded = read_ply(tmp_path / "object.ply")
    F = torch.eye(3) + 0.2 * torch.randn(400, 3, 3, generator=torch.Generator().manual_seed(14))
    F = torch.where(torch.linalg.det(F)[:, None, None] < 0, -F, F)
    a, b = deform_gaussians(gs, gs.means, F), deform_gaussians(loaded, loaded.means, F)
    torch.testing.assert_close(a.covariances(), b.covariances(), atol=1e-9, rtol=1e-4)
