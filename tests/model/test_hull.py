"""Visual-hull depth ranges (physgm.model.hull) against a sphere's analytic hull, and the Warp
kernel of the search against its torch twin."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from physgm.cameras import orbit_cameras, pixel_rays
from physgm.model.hull import _hull_depth_range_torch, hull_depth_range

RADIUS, DISTANCE, RES = 0.3, 1.8, 64


def sphere_views(azimuths: list[float]):
    """Exact masks of a sphere of RADIUS at the origin (pixel-centre rays that hit it)."""
    cams = orbit_cameras(azimuths, [0.0] * len(azimuths), DISTANCE, 34.0, RES, RES)
    origins, dirs = pixel_rays(cams)  # [V, H, W, 3]
    closest = -(origins * dirs).sum(-1)  # depth of the ray point nearest the centre
    miss = (origins + closest[..., None] * dirs).norm(dim=-1)  # its distance from the centre
    masks = (miss < RADIUS).float()[:, None]  # [V, 1, H, W]
    return cams, dirs, masks, closest, miss


def test_four_views_bound_the_sphere_and_match_its_analytic_hull():
    cams, dirs, masks, closest, miss = sphere_views([0.0, 90.0, 180.0, 270.0])
    lo, hi = hull_depth_range(masks[None], cams.c2w[None], cams.Ks[None], dirs[None], 0.001, 3.0, samples=32)
    lo, hi = lo[0], hi[0]
    chord = (RADIUS**2 - miss**2).clamp_min(0).sqrt()
    entry, exit_ = closest - chord, closest + chord
    core = miss < 0.8 * RADIUS  # away from the silhouette rim, where pixel masks are exact enough
    # the hull contains the object: the sphere's segment lies inside every range (up to the
    # 1.7 cm pixel footprint: a surface point may fall in a rim pixel whose centre ray misses)
    assert (lo[core] <= entry[core] + 0.01).all() and (hi[core] >= exit_[core] - 0.01).all()
    # and is tight: the central rays enter the hull where the side views' cones cross the axis,
    # at DISTANCE - DISTANCE * RADIUS / sqrt(DISTANCE^2 - RADIUS^2) (one pixel and one sample of slack)
    hull_entry = DISTANCE - DISTANCE * RADIUS / math.sqrt(DISTANCE**2 - RADIUS**2)
    centre = (miss < 0.02).nonzero()  # the 4 pixels around each image centre
    spacing_and_pixel = 0.05
    for view, row, col in centre.tolist():
        assert hull_entry - spacing_and_pixel <= lo[view, row, col] <= hull_entry + 0.02
        assert hi[view, row, col] - lo[view, row, col] < 0.8  # [near, far] is 3.0 long
    # pixels outside the mask make no Gaussians and keep [near, far]
    outside = masks[:, 0] == 0
    assert (lo[outside] == 0.001).all() and (hi[outside] == 3.0).all()


def test_one_view_keeps_the_full_range_and_bad_sample_counts_are_refused():
    cams, dirs, masks, *_ = sphere_views([30.0])
    lo, hi = hull_depth_range(masks[None], cams.c2w[None], cams.Ks[None], dirs[None], 0.01, 1.5)
    assert (lo == 0.01).all() and (hi == 1.5).all()
    with pytest.raises(ValueError, match="hull_samples"):
        hull_depth_range(masks[None], cams.c2w[None], cams.Ks[None], dirs[None], 0.01, 1.5, samples=1)


def test_unconfirmed_rays_fall_back_to_near_far():
    """A mask pixel that no other view confirms (here: view 2 is empty) keeps [near, far]."""
    cams, dirs, masks, *_ = sphere_views([0.0, 90.0])
    masks[1] = 0.0
    lo, hi = hull_depth_range(masks[None], cams.c2w[None], cams.Ks[None], dirs[None], 0.001, 2.0)
    assert (lo == 0.001).all() and (hi == 2.0).all()


def test_hull_prior_puts_every_gaussian_inside_its_range():
    """depth_prior="hull" end to end: Gaussian depths stay within the hull segment of their ray,
    and raw 0 (the initial head output) lands in the middle of it."""
    from physgm.model import PhysGM, PhysGMConfig

    cams, dirs, masks, *_ = sphere_views([0.0, 90.0, 180.0, 270.0])
    config = PhysGMConfig()
    config = replace(config, gaussian_head=replace(config.gaussian_head, depth_prior="hull", max_offset=0.0))
    model = PhysGM(config).eval()
    images = torch.rand(1, 4, 3, RES, RES, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        g = model(images, masks[None], cams.c2w[None], cams.Ks[None]).gaussians
    lo, hi = hull_depth_range(masks[None], cams.c2w[None], cams.Ks[None], dirs[None], 0.001, 2.0)
    lo, hi = lo.reshape(1, -1), hi.reshape(1, -1)
    assert g.valid.sum() > 1000
    assert (g.depths >= lo - 1e-5).all() and (g.depths <= hi + 1e-5).all()
    # the last layer starts near zero: depths start near the middle of the segment
    torch.testing.assert_close(g.depths[g.valid], (0.5 * (lo + hi))[g.valid], atol=0.02 * 2.0, rtol=0)


def test_ray_chunks_do_not_change_the_twin(monkeypatch):
    import physgm.model.hull as hull

    cams, dirs, masks, *_ = sphere_views([0.0, 90.0, 180.0])
    args = (masks[None], cams.c2w[None], cams.Ks[None], dirs[None], 0.001, 3.0)
    whole = _hull_depth_range_torch(*args)
    monkeypatch.setattr(hull, "RAY_CHUNK", 97)  # many chunks, the last one partial
    chunked = _hull_depth_range_torch(*args)
    torch.testing.assert_close(chunked, whole, rtol=0, atol=0)


def blob_views(azimuths: list[float], seed: int):
    """Masks of a random union of three spheres, seen from ``azimuths`` at two elevations: a
    non-convex object whose hull the views cut unevenly."""
    g = torch.Generator().manual_seed(seed)
    centres = (torch.rand(3, 3, generator=g) - 0.5) * 0.4
    radii = 0.1 + 0.15 * torch.rand(3, generator=g)
    elevations = [20.0 * (-1) ** k for k in range(len(azimuths))]
    cams = orbit_cameras(azimuths, elevations, DISTANCE, 34.0, RES, RES)
    origins, dirs = pixel_rays(cams)  # [V, H, W, 3]
    hit = torch.zeros(dirs.shape[:3], dtype=torch.bool)
    for c, r in zip(centres, radii, strict=True):
        closest = ((c - origins) * dirs).sum(-1)
        hit |= (origins + closest[..., None] * dirs - c).norm(dim=-1) < r
    return cams, dirs, hit.float()[:, None]


@pytest.mark.parametrize(
    "views",
    [
        lambda: sphere_views([0.0, 90.0, 180.0, 270.0])[:3],
        lambda: sphere_views([10.0, 130.0, 250.0])[:3],
        lambda: blob_views([0.0, 90.0, 180.0, 270.0], seed=1),
        lambda: blob_views([35.0, 100.0, 220.0, 300.0], seed=2),
    ],
)
def test_kernel_matches_its_torch_twin(views):
    """The Warp search and the torch twin find the same range; they may differ only where float
    rounding puts a sample on the other side of a pixel edge, by at most one sample spacing."""
    cams, dirs, masks = views()
    near, far, samples = 0.001, 3.0, 32
    args = (masks[None], cams.c2w[None], cams.Ks[None], dirs[None], near, far, samples)
    lo, hi = hull_depth_range(*args)
    lo_ref, hi_ref = _hull_depth_range_torch(*args)
    inside = masks[None, :, 0] > 0
    assert (hi - lo)[inside].max() < far - near  # the hull is found, not [near, far] everywhere
    spacing = (far - near) / (samples - 1)
    for got, ref in ((lo, lo_ref), (hi, hi_ref)):
        differs = (got - ref).abs() > 1e-5
        assert differs.float().mean() < 0.005
        assert ((got - ref).abs() <= spacing + 1e-5).all()
    outside = ~inside  # untouched by either
    assert (lo[outside] == near).all() and (hi[outside] == far).all()


@pytest.mark.gpu
def test_kernel_on_cuda_matches_the_cpu_kernel():
    """The same kernel launched on the tensors' CUDA device gives the CPU's ranges."""
    cams, dirs, masks = blob_views([0.0, 90.0, 180.0, 270.0], seed=3)
    args = (masks[None], cams.c2w[None], cams.Ks[None], dirs[None])
    lo, hi = hull_depth_range(*args, 0.001, 3.0)
    lo_cuda, hi_cuda = hull_depth_range(*(a.cuda() for a in args), 0.001, 3.0)
    assert lo_cuda.is_cuda
    for got, ref in ((lo_cuda.cpu(), lo), (hi_cuda.cpu(), hi)):
        assert ((got - ref).abs() > 1e-5).float().mean() < 0.005
