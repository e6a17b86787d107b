"""Culling, empty scenes, zero opacity, backgrounds and batching."""

from __future__ import annotations

import pytest
import torch

from physgm.render import Renderer, rasterize

BACKENDS = ("warp", "torch")


def args_of(s: dict) -> list:
    return [
        s["means"],
        s["quats"],
        s["scales"],
        s["opacities"],
        s["colors"],
        s["viewmats"],
        s["Ks"],
        s["width"],
        s["height"],
    ]


@pytest.mark.parametrize("backend", BACKENDS)
def test_gaussians_behind_the_camera_give_the_background(backend, scene, kit):
    s = kit.to(scene, requires_grad=True)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))  # turn every camera around
    s["viewmats"] = flip @ s["viewmats"]
    s["viewmats"][:, 2, 3] = -0.6  # object (radius 0.5 m) now at z in [-1.1, -0.1] m
    bg = torch.tensor([0.1, 0.2, 0.3])
    rgb, alpha, meta = rasterize(*args_of(s), background=bg, backend=backend)
    assert torch.equal(rgb, bg.expand_as(rgb))
    assert torch.equal(alpha, torch.zeros_like(alpha))
    assert int(meta["n_visible"].sum()) == 0
    rgb.sum().backward()  # still differentiable: zero gradients of the right shapes
    for key in kit.GRAD_KEYS:
        assert s[key].grad.shape == s[key].shape and not s[key].grad.any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_near_plane_culls_gaussians_closer_than_it(backend):
    gauss = dict(
        means=torch.tensor([[0.0, 0.0, 0.3]]),
        quats=torch.tensor([[1.0, 0, 0, 0]]),
        scales=torch.full((1, 3), 0.01),
        opacities=torch.tensor([0.9]),
        colors=torch.ones(1, 3),
    )
    K = torch.tensor([[[30.0, 0.0, 16.0], [0.0, 30.0, 16.0], [0.0, 0.0, 1.0]]])
    shown, _, _ = rasterize(
        **gauss, viewmats=torch.eye(4)[None], Ks=K, width=32, height=32, backend=backend, near_plane=0.2
    )
    culled, _, meta = rasterize(
        **gauss, viewmats=torch.eye(4)[None], Ks=K, width=32, height=32, backend=backend, near_plane=0.5
    )
    assert shown.max() > 0.5
    assert not culled.any() and int(meta["n_visible"][0]) == 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_scene(backend, scene, kit):
    s = kit.to({**scene, **kit.random_gaussians(0, seed=0)}, requires_grad=True)
    bg = torch.tensor([0.5, 0.25, 1.0])
    rgb, alpha, meta = rasterize(*args_of(s), background=bg, backend=backend)
    assert rgb.shape == (3, s["height"], s["width"], 3) and alpha.shape == (3, s["height"], s["width"], 1)
    assert torch.equal(rgb, bg.expand_as(rgb)) and not alpha.any()
    assert meta["radii"].shape == (3, 0, 2)
    (rgb.sum() + alpha.sum()).backward()
    for key in kit.GRAD_KEYS:
        assert s[key].grad is not None and s[key].grad.shape == s[key].shape
    _, alpha, _ = rasterize(*args_of(s), backend=backend)
    alpha.sum().backward()  # alpha alone (a mask loss) must be differentiable too


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_opacity_gaussians_change_nothing(backend, scene, kit):
    s = kit.to(scene)
    extra = kit.to(kit.random_gaussians(50, seed=9))
    extra["opacities"] = torch.zeros(50)
    merged = {k: torch.cat([s[k], extra[k]]) if k in kit.GRAD_KEYS else v for k, v in s.items()}
    rgb, alpha, meta = rasterize(*args_of(s), backend=backend)
    rgb2, alpha2, meta2 = rasterize(*args_of(merged), backend=backend)
    assert torch.equal(rgb, rgb2) and torch.equal(alpha, alpha2)
    assert torch.equal(meta["n_visible"], meta2["n_visible"])
    assert not meta2["radii"][:, 300:].any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_background_per_camera(backend, scene, kit):
    s = kit.to(scene)
    bg = torch.rand(3, 3, generator=torch.Generator().manual_seed(0))  # [C, 3]
    rgb0, alpha, _ = rasterize(*args_of(s), backend=backend)
    rgb, _, _ = rasterize(*args_of(s), background=bg, backend=backend)
    torch.testing.assert_close(rgb, rgb0 + (1 - alpha) * bg[:, None, None, :], atol=1e-6, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_batch_equals_a_loop_over_the_batch(backend, kit):
    width, height, B, C = 36, 28, 2, 3
    gauss = [kit.to(kit.random_gaussians(200, seed=10 + b)) for b in range(B)]
    cams = [kit.orbit_cameras(C, width, height, seed=b) for b in range(B)]
    stacked = {k: torch.stack([g[k] for g in gauss]).requires_grad_(True) for k in kit.GRAD_KEYS}
    viewmats = torch.stack([c[0] for c in cams]).float()  # [B, C, 4, 4]
    Ks = torch.stack([c[1] for c in cams]).float()
    bg = torch.rand(B, C, 3, generator=torch.Generator().manual_seed(1))
    rgb, alpha, meta = rasterize(
        **stacked, viewmats=viewmats, Ks=Ks, width=width, height=height, background=bg, backend=backend
    )
    assert rgb.shape == (B, C, height, width, 3) and meta["radii"].shape == (B, C, 200, 2)
    rgb.square().sum().backward()
    for b in range(B):
        single = {k: gauss[b][k].clone().requires_grad_(True) for k in kit.GRAD_KEYS}
        rgb_b, alpha_b, meta_b = rasterize(
            **single,
            viewmats=viewmats[b],
            Ks=Ks[b],
            width=width,
            height=height,
            background=bg[b],
            backend=backend,
        )
        rgb_b.square().sum().backward()
        torch.testing.assert_close(rgb[b], rgb_b, atol=1e-6, rtol=0)
        torch.testing.assert_close(alpha[b], alpha_b, atol=1e-6, rtol=0)
        assert torch.equal(meta["n_visible"][b], meta_b["n_visible"])
        for k in kit.GRAD_KEYS:
            torch.testing.assert_close(stacked[k].grad[b], single[k].grad, atol=1e-5, rtol=1e-4)


def test_several_leading_dims_and_the_renderer_object(scene, kit):
    s = kit.to(scene)
    lead = (2, 2)
    batched = {k: s[k].expand(*lead, *s[k].shape).contiguous() for k in (*kit.GRAD_KEYS, "viewmats", "Ks")}
    renderer = Renderer(backend="warp", tile_size=8, num_threads=1)
    rgb, alpha, meta = renderer(**batched, width=s["width"], height=s["height"])
    ref, _, _ = rasterize(*args_of(s))
    assert rgb.shape == (*lead, 3, s["height"], s["width"], 3)
    assert meta["n_visible"].shape == (*lead, 3)
    for i in range(2):
        for j in range(2):
            torch.testing.assert_close(rgb[i, j], ref, atol=1e-6, rtol=0)
