"""CUDA paths: the same Warp code on the GPU, and the gsplat backend (skipped without CUDA)."""

from __future__ import annotations

import pytest
import torch

from physgm.render import rasterize

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
]


def _render(s: dict, device: str, backend: str):
    keys = ("means", "quats", "scales", "opacities", "colors")
    params = {k: s[k].to(device).requires_grad_(True) for k in keys}
    rgb, alpha, _ = rasterize(
        **params,
        viewmats=s["viewmats"].to(device),
        Ks=s["Ks"].to(device),
        width=s["width"],
        height=s["height"],
        backend=backend,
    )
    (rgb.square().sum() + alpha.sum()).backward()
    return rgb.detach().cpu(), alpha.detach().cpu(), {k: p.grad.cpu() for k, p in params.items()}


def test_warp_on_cuda_matches_torch_on_cpu(scene, kit):
    s = kit.to(scene)
    rgb_t, alpha_t, grads_t = _render(s, "cpu", "torch")
    rgb_w, alpha_w, grads_w = _render(s, "cuda", "warp")
    assert (rgb_w - rgb_t).abs().max() <= 1e-4 and (alpha_w - alpha_t).abs().max() <= 1e-4
    for k, g in grads_t.items():
        assert (grads_w[k] - g).norm() <= 1e-3 * g.norm(), k


def test_gsplat_matches_torch(scene, kit):
    pytest.importorskip("gsplat")
    s = kit.to(scene)
    rgb_t, alpha_t, _ = _render(s, "cpu", "torch")
    rgb_g, alpha_g, _ = _render(s, "cuda", "gsplat")
    # gsplat bins with its own 3-sigma box and stops at T <= 1e-4: a few pixels differ slightly
    assert (rgb_g - rgb_t).abs().mean() <= 1e-3 and (rgb_g - rgb_t).abs().max() <= 2e-2
    assert (alpha_g - alpha_t).abs().mean() <= 1e-3
