"""Bad inputs stop with a ValueError that names the argument and what was expected."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

from physgm.render import Renderer, rasterize


@pytest.fixture
def good(scene, kit):
    s = kit.to(scene)
    return dict(
        means=s["means"],
        quats=s["quats"],
        scales=s["scales"],
        opacities=s["opacities"],
        colors=s["colors"],
        viewmats=s["viewmats"],
        Ks=s["Ks"],
        width=s["width"],
        height=s["height"],
    )


def nan_at(x: torch.Tensor) -> torch.Tensor:
    x = x.clone()
    x.view(-1)[0] = float("nan")
    return x


CASES = [
    # (override, regex the message must match)
    (lambda g: {"means": g["means"][:, :2]}, r"means must have shape \[\.\.\., N, 3\], got \(300, 2\)"),
    (lambda g: {"means": torch.zeros(5, 4)}, r"means must have shape \[\.\.\., N, 3\], got \(5, 4\)"),
    (lambda g: {"quats": g["quats"][:-1]}, r"quats must have shape \[300, 4\]"),
    (lambda g: {"scales": g["scales"][None]}, r"scales must have shape \[300, 3\]"),
    (lambda g: {"opacities": g["opacities"][:, None]}, r"opacities must have shape \[300\]"),
    (lambda g: {"colors": g["colors"][:, :1]}, r"colors must have shape \[\.\.\., N, 3\]"),
    (lambda g: {"viewmats": g["viewmats"][:, :3]}, r"viewmats must have shape \[\.\.\., C, 4, 4\]"),
    (lambda g: {"Ks": g["Ks"][:2]}, r"Ks must have shape \[3, 3, 3\]"),
    (lambda g: {"viewmats": g["viewmats"][None].expand(2, 3, 4, 4)}, r"viewmats must have shape \[3, 4, 4\]"),
    (lambda g: {"means": g["means"].long()}, r"means must be a floating-point tensor"),
    (lambda g: {"colors": g["colors"].double()}, r"one dtype"),
    (lambda g: {"means": g["means"].tolist()}, r"means must be a torch\.Tensor"),
    (lambda g: {"means": nan_at(g["means"])}, r"means contains NaN or Inf"),
    (lambda g: {"viewmats": nan_at(g["viewmats"])}, r"viewmats contains NaN or Inf"),
    (lambda g: {"scales": -g["scales"]}, r"scales must be non-negative.*log-scales"),
    (lambda g: {"opacities": g["opacities"] * 4 - 2}, r"opacities must lie in \[0, 1\].*sigmoid"),
    (lambda g: {"quats": torch.zeros_like(g["quats"])}, r"quats must have non-zero norm"),
    (lambda g: {"quats": torch.cat([g["quats"][:-1], torch.zeros(1, 4)])}, r"quats must have non-zero norm"),
    (lambda g: {"scales": torch.cat([g["scales"][:-1], -torch.ones(1, 3)])}, r"scales must be non-negative"),
    (
        lambda g: {"opacities": torch.cat([g["opacities"][:-1], torch.tensor([1.5])])},
        r"opacities must lie in",
    ),
    (
        lambda g: {"colors": torch.cat([g["colors"][:-1], torch.tensor([[0.0, float("inf"), 0.0]])])},
        r"colors contains NaN or Inf",
    ),
    (lambda g: {"Ks": -g["Ks"]}, r"Ks must have positive focal lengths"),
    (lambda g: {"width": 0}, r"width must be a positive int"),
    (lambda g: {"height": -3}, r"height must be a positive int"),
    (lambda g: {"width": 32.0}, r"width must be a positive int"),
    (lambda g: {"background": torch.zeros(4)}, r"background must have shape \[3\] or \[3, 3\]"),
    (lambda g: {"near_plane": 0.0}, r"near_plane and far_plane"),
    (lambda g: {"eps2d": -1.0}, r"eps2d must be >= 0"),
    (lambda g: {"backend": "opengl"}, r"backend must be one of \['gsplat', 'torch', 'warp'\]"),
    (lambda g: {"tile_size": 0}, r"tile_size must be a positive int"),
]


@pytest.mark.parametrize("case", range(len(CASES)))
def test_bad_input_raises_value_error(good, case):
    override, pattern = CASES[case]
    with pytest.raises(ValueError, match=pattern):
        rasterize(**{**good, **override(good)})


def test_renderer_rejects_unknown_backend():
    with pytest.raises(ValueError, match="backend must be one of"):
        Renderer(backend="vulkan")


def test_gsplat_backend_on_cpu_says_how_to_switch(good):
    with pytest.raises(ValueError, match=r"gsplat.*CUDA.*backend='warp'"):
        rasterize(**good, backend="gsplat")


@wp.kernel
def _copy_vec3(src: wp.array(dtype=wp.vec3), dst: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    dst[i] = src[i]


def test_warp_views_check_their_element_type_and_keep_the_memory():
    from physgm.render.warp_backend import _arr

    wp.init()
    base = torch.arange(24, dtype=torch.float32).reshape(4, 6)
    view = _arr(base[:, ::2], wp.vec3)  # a non-contiguous slice becomes a contiguous copy that the view holds
    del base
    assert (view.ndim, view.shape[0], view.strides[0]) == (1, 4, 12)
    out = wp.zeros(4, dtype=wp.vec3)
    wp.launch(_copy_vec3, 4, [view, out])  # a kernel reads the tensor's memory through the view
    np.testing.assert_array_equal(out.numpy(), np.arange(24, dtype=np.float32).reshape(4, 6)[:, ::2])
    mats = _arr(torch.zeros(5, 2, 4, 4), wp.mat44)
    assert (mats.ndim, mats.shape[0], mats.shape[1], mats.strides[0], mats.strides[1]) == (2, 5, 2, 128, 64)
    for bad, dtype in (
        (torch.zeros(5, 3, dtype=torch.float64), wp.vec3),
        (torch.zeros(5, 4), wp.vec3),
        (torch.zeros(5), wp.vec2),
        (torch.zeros(5, dtype=torch.int64), wp.int32),
    ):
        with pytest.raises(ValueError, match="does not hold"):
            _arr(bad, dtype)


def test_finite_values_whose_sum_overflows_are_accepted(good):
    """The finiteness check's fast path (the sum) overflows to inf here; the exact test decides."""
    from physgm.render.validate import validate_inputs

    colors = torch.full_like(good["colors"], 3.0e38)  # finite, but their float32 sum is inf
    assert not torch.isfinite(colors.sum())
    args = {**good, "colors": colors}
    validate_inputs(
        tuple(args[k] for k in ("means", "quats", "scales", "opacities", "colors")),
        (args["viewmats"], args["Ks"]),
        args["width"],
        args["height"],
        None,
        0.01,
        1e10,
        0.3,
    )
