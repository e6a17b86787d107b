"""The CPU tile layout's SIMD rows: its exp, its tile-size limit, and agreement with the pixel layout."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

from physgm.render import warp_tile_kernels as T
from physgm.render.batch import SplatBatch
from physgm.render.settings import RasterSettings
from physgm.render.warp_backend import rasterize_warp


def run_exp(x: np.ndarray) -> np.ndarray:
    rows = wp.array(x.reshape(-1, T.LANES), dtype=T.vec16, device="cpu")
    out = wp.zeros_like(rows)
    wp.launch(T.exp16_kernel, rows.shape[0], [rows, out], device="cpu")
    return out.numpy().reshape(-1)


def test_exp_is_as_accurate_as_a_float32_exp():
    # the range the kernels use: alpha >= 1/255 needs q <= 2 ln 255 + margin, so x >= -5.6;
    # lanes down to -15 are still computed before they are masked
    x = np.linspace(-15.0, 0.0, 16 * 20000, dtype=np.float32)
    got = run_exp(x).astype(np.float64)
    rel = np.abs(got / np.exp(x.astype(np.float64)) - 1.0)
    assert rel.max() <= 1.5e-7  # measured 1.0e-7; numpy's float32 exp: 2.0e-7
    assert run_exp(np.zeros(16, np.float32))[0] == 1.0


def test_exp_clamps_below_minus_15():
    got = run_exp(np.full(16, -40.0, np.float32))
    np.testing.assert_allclose(got, np.exp(-15.0), rtol=2e-7)


def render(scene: dict, kit, **settings):
    s = kit.to(scene, torch.float32, requires_grad=True)
    batch = SplatBatch(*(s[k][None] for k in kit.GRAD_KEYS), s["viewmats"][None], s["Ks"][None])
    rgb, alpha, _ = rasterize_warp(batch, RasterSettings(s["width"], s["height"], **settings))
    weights = torch.randn(rgb.shape, generator=torch.Generator().manual_seed(2))
    ((rgb * weights).sum() + alpha.sum()).backward()
    return rgb.detach(), alpha.detach(), {k: s[k].grad for k in kit.GRAD_KEYS}


def test_tile_layout_matches_the_pixel_layout(scene, kit):
    # 40 x 32 px: the last tile column is 8 px wide, so lanes 8-15 of its rows are off the image
    rgb_t, alpha_t, grads_t = render(scene, kit, warp_layout="tile")
    rgb_p, alpha_p, grads_p = render(scene, kit, warp_layout="pixel")
    assert alpha_p.max() > 0.5
    assert (rgb_t - rgb_p).abs().max() <= 1e-5
    assert (alpha_t - alpha_p).abs().max() <= 1e-5
    for name, ref in grads_p.items():
        assert (grads_t[name] - ref).norm() <= 1e-4 * ref.norm(), name


def test_tiles_wider_than_a_row_use_the_pixel_layout(scene, kit):
    with pytest.raises(ValueError, match="at most 16 px"):
        render(scene, kit, warp_layout="tile", tile_size=32)
    rgb_auto, _, _ = render(scene, kit, tile_size=32)  # auto: the pixel layout
    rgb_pixel, _, _ = render(scene, kit, tile_size=32, warp_layout="pixel")
    assert torch.equal(rgb_auto, rgb_pixel)
