"""Single Gaussians and stacks on the optical axis against closed-form EWA splatting.

Camera at the origin looking down +z (identity viewmat). For an isotropic Gaussian of std s at
depth Z on the axis, the 2D covariance is ((f s / Z)^2 + eps2d) I, so a pixel at offset d from
the projected mean gets alpha = min(0.99, o exp(-d^2 / (2 sigma^2))), or 0 when below 1/255.
"""

from __future__ import annotations

import math

import pytest
import torch

from physgm.render import rasterize

BACKENDS = ("warp", "torch")
EPS2D = 0.3


def one_gaussian(mean, scale, opacity, color=(0.2, 0.6, 1.0)):
    return dict(
        means=torch.tensor([mean], dtype=torch.float32),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        scales=torch.full((1, 3), float(scale)),
        opacities=torch.tensor([float(opacity)]),
        colors=torch.tensor([color], dtype=torch.float32),
    )


def camera(focal, cx, cy):
    K = torch.tensor([[[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]]])
    return torch.eye(4)[None], K


def expected_alpha(width, height, mean2d, sigma2, opacity):
    """Closed-form alpha image [H, W] for an isotropic 2D Gaussian of variance sigma2 (px^2)."""
    v, u = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    d2 = (u + 0.5 - mean2d[0]) ** 2 + (v + 0.5 - mean2d[1]) ** 2
    alpha = torch.clamp(opacity * torch.exp(-0.5 * d2.double() / sigma2), max=0.99)
    return torch.where(alpha < 1 / 255, torch.zeros_like(alpha), alpha)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize(
    "scale, opacity, mean2d, size",
    [
        (0.02, 0.8, (20.5, 16.5), (40, 32)),  # centred
        (1e-8, 0.7, (7.3, 9.9), (40, 32)),  # point-like: only the 0.3 px^2 dilation is left
        (10.0, 0.6, (20.0, 16.0), (40, 32)),  # std 10 m at 2 m: nearly flat over the image
        (0.03, 0.9, (0.0, 0.0), (40, 32)),  # on the image corner: a quarter is visible
        (0.08, 0.9, (-2.5, 12.0), (40, 32)),  # centre outside the left border
        (0.02, 0.8, (30.2, 4.7), (37, 21)),  # non-square, sizes not multiples of the tile
        (0.05, 0.02, (18.0, 10.0), (40, 32)),  # faint: the 1/255 cut-off shapes the footprint
        (0.05, 1.0, (18.5, 10.5), (40, 32)),  # opaque: alpha clamped at 0.99
    ],
)
def test_single_gaussian_matches_closed_form(backend, scale, opacity, mean2d, size):
    width, height = size
    focal, depth = 40.0, 2.0
    viewmats, Ks = camera(focal, cx=width / 2, cy=height / 2)
    # place the mean so that it projects to mean2d
    x = (mean2d[0] - width / 2) * depth / focal
    y = (mean2d[1] - height / 2) * depth / focal
    gauss = one_gaussian((x, y, depth), scale, opacity)
    rgb, alpha, meta = rasterize(
        **gauss, viewmats=viewmats, Ks=Ks, width=width, height=height, backend=backend
    )
    # off-axis the Jacobian adds a small anisotropy; compute the exact 2D covariance here
    J = torch.tensor(
        [[focal / depth, 0.0, -focal * x / depth**2], [0.0, focal / depth, -focal * y / depth**2]],
        dtype=torch.float64,
    )
    cov = scale**2 * J @ J.T + EPS2D * torch.eye(2, dtype=torch.float64)
    if abs(cov[0, 1]) < 1e-9 and abs(cov[0, 0] - cov[1, 1]) < 1e-9:
        want = expected_alpha(width, height, mean2d, float(cov[0, 0]), opacity)
    else:  # general closed form with the inverse covariance
        v, u = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
        d = torch.stack([u + 0.5 - mean2d[0], v + 0.5 - mean2d[1]], -1).double()
        q = torch.einsum("hwi,ij,hwj->hw", d, torch.linalg.inv(cov), d)
        want = torch.clamp(opacity * torch.exp(-0.5 * q), max=0.99)
        want = torch.where(want < 1 / 255, torch.zeros_like(want), want)
    assert want.max() > 0  # the test really draws something
    torch.testing.assert_close(alpha[0, :, :, 0].double(), want, atol=2e-6, rtol=1e-4)
    torch.testing.assert_close(
        rgb[0].double(), want[..., None] * gauss["colors"][0].double(), atol=2e-6, rtol=1e-4
    )
    assert int(meta["n_visible"][0]) == 1
    if opacity == 1.0:
        assert float(alpha.max()) == pytest.approx(0.99, abs=1e-7)


@pytest.mark.parametrize("backend", BACKENDS)
def test_depth_order_and_early_stop(backend):
    # four opaque-ish Gaussians on the axis; the centre pixel sees alpha 0.95 from each. After
    # three, T = 0.05^3 = 1.25e-4; the fourth would take it to 6.25e-6 < 1e-4, so it is left out.
    depths = torch.tensor([2.3, 2.0, 2.2, 2.1])  # unsorted on purpose
    colors = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    means = torch.stack([torch.zeros(4), torch.zeros(4), depths], -1)
    gauss = dict(
        means=means,
        quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(4, 1),
        scales=torch.full((4, 3), 0.05),
        opacities=torch.full((4,), 0.95),
        colors=colors,
    )
    viewmats, Ks = camera(40.0, cx=20.5, cy=16.5)  # centre pixel (20, 16) sits on the axis
    bg = torch.tensor([0.0, 1.0, 0.0])
    rgb, alpha, _ = rasterize(
        **gauss, viewmats=viewmats, Ks=Ks, width=40, height=32, background=bg, backend=backend
    )
    centre = rgb[0, 16, 20]
    t3 = 0.05**3
    assert float(alpha[0, 16, 20, 0]) == pytest.approx(1 - t3, abs=1e-6)
    assert float(centre[0]) == pytest.approx(1 - t3, abs=1e-6)  # red from the three in front
    assert float(centre[1]) == pytest.approx(t3, abs=1e-6)  # background through T
    assert float(centre[2]) == 0.0  # the blue one behind was never composited

    # a red Gaussian in front of a blue one: rgb = a_r red + (1 - a_r) a_b blue at the centre
    two = dict(
        means=torch.tensor([[0.0, 0.0, 2.5], [0.0, 0.0, 2.0]]),
        quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(2, 1),
        scales=torch.full((2, 3), 0.05),
        opacities=torch.tensor([0.7, 0.6]),
        colors=torch.tensor([[0.0, 0, 1], [1.0, 0, 0]]),
    )
    rgb, _, _ = rasterize(**two, viewmats=viewmats, Ks=Ks, width=40, height=32, backend=backend)
    torch.testing.assert_close(rgb[0, 16, 20], torch.tensor([0.6, 0.0, 0.4 * 0.7]), atol=1e-6, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_quaternions_are_normalised_inside(backend, scene, kit):
    s = kit.to(scene, requires_grad=True)
    args = dict(viewmats=s["viewmats"], Ks=s["Ks"], width=s["width"], height=s["height"], backend=backend)
    rgb, _, _ = rasterize(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], **args)
    rgb.square().sum().backward()
    scaled = (3.7 * s["quats"]).detach()
    rgb2, _, _ = rasterize(s["means"], scaled, s["scales"], s["opacities"], s["colors"], **args)
    torch.testing.assert_close(rgb2, rgb, atol=1e-5, rtol=0)
    # the image is invariant to |q|, so the gradient has no radial part
    grad, q = s["quats"].grad, s["quats"].detach()
    radial = (grad * q).sum(-1) / q.norm(dim=-1)
    assert grad.norm() > 0
    assert radial.abs().max() <= 1e-4 * grad.norm(dim=-1).max()
    assert not math.isnan(float(grad.sum()))
