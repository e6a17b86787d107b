"""Warp backend vs the plain-torch twin (forward to 1e-4, gradients to 1e-3), and the twin vs
finite differences."""

from __future__ import annotations

import pytest
import torch

from physgm.render import rasterize
from physgm.render.batch import SplatBatch
from physgm.render.settings import RasterSettings
from physgm.render.torch_backend import rasterize_torch
from physgm.render.warp_backend import rasterize_warp

LAYOUTS = ("tile", "pixel")


def run(scene: dict, kit, backend: str, dtype=torch.float32, **settings):
    """Renders `scene` ([N, ...] Gaussians, [C, ...] cameras) with gradients of a fixed loss.

    backend "torch" or "warp:<layout>". Returns rgb, alpha, meta, {name: grad}.
    """
    s = kit.to(scene, dtype, requires_grad=True)
    # add the batch dim the backends expect
    batch = SplatBatch(*(s[k][None] for k in kit.GRAD_KEYS), s["viewmats"][None], s["Ks"][None])
    if backend == "torch":
        rgb, alpha, meta = rasterize_torch(batch, RasterSettings(s["width"], s["height"]))
    else:
        layout = backend.split(":")[1]
        st = RasterSettings(s["width"], s["height"], warp_layout=layout, **settings)
        rgb, alpha, meta = rasterize_warp(batch, st)
    gen = torch.Generator().manual_seed(7)
    w_rgb = torch.randn(rgb.shape, generator=gen, dtype=torch.float64).to(dtype)
    w_alpha = torch.randn(alpha.shape, generator=gen, dtype=torch.float64).to(dtype)
    ((rgb * w_rgb).sum() + (alpha * w_alpha).sum()).backward()
    grads = {k: s[k].grad for k in kit.GRAD_KEYS}
    return rgb.detach(), alpha.detach(), meta, grads


def assert_grads_close(grads_test: dict, grads_ref: dict, rel: float = 1e-3) -> None:
    for name, ref in grads_ref.items():
        err = (grads_test[name].double() - ref.double()).norm()
        assert err <= rel * ref.double().norm(), (
            f"{name}: |g - g_ref| = {err:.3e}, |g_ref| = {ref.norm():.3e}"
        )


@pytest.mark.parametrize("binning", ["counting", "sort"])
@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("seed", [0, 1])
def test_warp_forward_and_grads_match_torch(scene, kit, layout, seed, binning):
    scene = {**scene, **kit.random_gaussians(300, seed=seed)}
    rgb_t, alpha_t, meta_t, grads_t = run(scene, kit, "torch")
    rgb_w, alpha_w, meta_w, grads_w = run(scene, kit, f"warp:{layout}", warp_binning=binning)
    assert alpha_t.max() > 0.5  # the scene really covers pixels
    assert (rgb_w - rgb_t).abs().max() <= 1e-4
    assert (alpha_w - alpha_t).abs().max() <= 1e-4
    assert torch.equal(meta_w["n_visible"], meta_t["n_visible"])
    assert torch.equal(meta_w["n_intersections"], meta_t["n_intersections"])
    assert torch.equal(meta_w["radii"], meta_t["radii"])
    assert_grads_close(grads_w, grads_t)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_dense_opaque_scene_with_early_stop(scene, kit, layout):
    # 600 nearly opaque Gaussians: most object pixels stop compositing early
    gauss = kit.random_gaussians(600, seed=3, scale=(0.03, 0.08))
    gauss["opacities"] = 0.8 + 0.2 * gauss["opacities"]
    scene = {**scene, **gauss}
    rgb_t, alpha_t, _, grads_t = run(scene, kit, "torch")
    rgb_w, alpha_w, _, grads_w = run(scene, kit, f"warp:{layout}")
    assert (alpha_t > 1 - 1e-3).float().mean() > 0.2  # early stop reached on many pixels
    assert (rgb_w - rgb_t).abs().max() <= 1e-4
    assert (alpha_w - alpha_t).abs().max() <= 1e-4
    assert_grads_close(grads_w, grads_t)


@pytest.mark.parametrize("output", ["rgb", "alpha"])
def test_a_loss_on_one_output_gets_the_twins_gradients(scene, kit, output):
    # only one output feeds the loss: the backward gets zeros for the other
    grads = {}
    for backend in ("torch", "warp"):
        s = kit.to(scene, torch.float32, requires_grad=True)
        args = [s[k] for k in kit.GRAD_KEYS] + [s["viewmats"], s["Ks"], s["width"], s["height"]]
        rgb, alpha, _ = rasterize(*args, backend=backend)
        out = rgb if output == "rgb" else alpha
        weights = torch.randn(out.shape, generator=torch.Generator().manual_seed(3))
        (out * weights).sum().backward()
        # alpha does not depend on the colours: the twin leaves their gradient None
        grads[backend] = {
            k: torch.zeros_like(s[k]) if s[k].grad is None else s[k].grad for k in kit.GRAD_KEYS
        }
    assert grads["torch"]["means"].abs().sum() > 0
    assert_grads_close(grads["warp"], grads["torch"])


def test_tile_size_and_threads_do_not_change_the_result(scene, kit):
    rgb_a, alpha_a, _, grads_a = run(scene, kit, "warp:tile", tile_size=16, num_threads=2)
    rgb_b, alpha_b, _, grads_b = run(scene, kit, "warp:tile", tile_size=8, num_threads=1)
    assert torch.equal(rgb_a, rgb_b) and torch.equal(alpha_a, alpha_b)
    assert_grads_close(grads_b, grads_a, rel=1e-6)


def test_float64_inputs_give_float64_outputs(scene, kit):
    s = kit.to(scene, torch.float64)
    args = [s[k] for k in kit.GRAD_KEYS] + [s["viewmats"], s["Ks"], s["width"], s["height"]]
    rgb_w, alpha_w, _ = rasterize(*args, backend="warp")
    rgb_t, alpha_t, _ = rasterize(*args, backend="torch")
    assert rgb_w.dtype == torch.float64 and alpha_w.dtype == torch.float64
    assert (rgb_w - rgb_t).abs().max() <= 1e-4


def test_torch_twin_matches_finite_differences(kit):
    # tiny float64 scene: 4 Gaussians, 2 cameras, 12 x 10 px, nowhere near a threshold
    width, height = 12, 10
    viewmats, Ks = kit.orbit_cameras(2, width, height, distance=2.0, focal=14.0)
    gauss = kit.random_gaussians(4, seed=5, radius=0.3, scale=(0.08, 0.15))
    gauss["opacities"] = 0.3 + 0.5 * gauss["opacities"]
    inputs = tuple(gauss[k][None].clone().requires_grad_(True) for k in kit.GRAD_KEYS)
    settings = RasterSettings(width, height)

    gen = torch.Generator().manual_seed(0)
    w_rgb = torch.randn(3, 2, height, width, 3, generator=gen, dtype=torch.float64)
    w_alpha = torch.randn(3, 2, height, width, 1, generator=gen, dtype=torch.float64)

    def render(*params):
        # three random linear read-outs of rgb and alpha: the full Jacobian of 960 outputs
        # would need 960 backward passes, these need three
        rgb, alpha, _ = rasterize_torch(SplatBatch(*params, viewmats[None], Ks[None]), settings)
        return (w_rgb * rgb).sum((1, 2, 3, 4)) + (w_alpha * alpha).sum((1, 2, 3, 4))

    _, alpha, _ = rasterize_torch(SplatBatch(*inputs, viewmats[None], Ks[None]), settings)
    assert alpha.max() > 0.3
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_tile_ranges_cover_every_tile_once_and_balance_the_work():
    from physgm.render.warp_backend import _tile_ranges

    work = torch.tensor([1, 1, 50, 1, 1, 1, 30, 1, 1, 13], dtype=torch.int32)
    ranges = _tile_ranges(work, 2)
    assert [r[0] for r in ranges] == [0, ranges[0][1]] and sum(r[1] for r in ranges) == 10
    halves = [int(work[a : a + n].sum()) for a, n in ranges]
    assert halves == [52, 48]  # the best cut; before the 50-tile it would be 2 vs 98
    assert _tile_ranges(work, 1) == [(0, 10)]
    skewed = torch.tensor([100] + [1] * 9, dtype=torch.int32)
    assert _tile_ranges(skewed, 2) == [(0, 1), (1, 9)]  # never an empty range
    three = _tile_ranges(torch.ones(9, dtype=torch.int32), 3)
    assert three == [(0, 3), (3, 3), (6, 3)]


def test_counting_and_sort_binning_agree_exactly_with_depth_ties(scene, kit):
    """Both binnings order a tile's entries by depth and, at equal depth, by Gaussian index."""
    g = kit.random_gaussians(200, seed=4)
    # Gaussians 100.. sit exactly where 0..99 are (equal depth in every camera), other colours
    g["means"][100:] = g["means"][:100]
    g["opacities"][:] = 0.9
    scene = {**scene, **g}
    rgb_c, alpha_c, _, grads_c = run(scene, kit, "warp:tile", warp_binning="counting")
    rgb_s, alpha_s, _, grads_s = run(scene, kit, "warp:tile", warp_binning="sort")
    rgb_t, _, _, _ = run(scene, kit, "torch")
    assert torch.equal(rgb_c, rgb_s) and torch.equal(alpha_c, alpha_s)
    for name in grads_c:
        assert torch.equal(grads_c[name], grads_s[name]), name
    assert (rgb_c - rgb_t).abs().max() <= 1e-4
    with pytest.raises(ValueError, match="warp_binning"):
        RasterSettings(16, 16, warp_binning="radix")
    with pytest.raises(ValueError, match="near_plane"):
        RasterSettings(16, 16, near_plane=0.0)  # both binnings sort by the bits of positive depths
