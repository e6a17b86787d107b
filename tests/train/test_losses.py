"""Stage-1 loss terms against hand-computed values."""

import math

import pytest
import torch

from physgm.model.posterior import PhysicsPosterior
from physgm.train.losses import PretrainLossConfig, anisotropy_penalty, pretrain_losses, token_anchor


def test_anisotropy_penalty_is_the_mean_log_excess_over_valid_gaussians():
    scales = torch.tensor([[[1.0, 1.0, 1.0], [0.5, 1.0, 8.0], [1.0, 2.0, 400.0]]])
    valid = torch.tensor([[True, True, False]])  # the needle is outside the mask: free
    # sphere: ratio 1 -> 0; second: ratio 16 -> log 16 - log 4 = log 4; mean over 2 valid
    assert anisotropy_penalty(scales, valid, 4.0).item() == pytest.approx(math.log(4.0) / 2, rel=1e-6)
    assert anisotropy_penalty(scales, torch.zeros_like(valid), 4.0).item() == 0.0


def test_anisotropy_penalty_gradient_shrinks_the_ratio():
    scales = torch.tensor([[[0.01, 0.5, 1.0]]], requires_grad=True)
    anisotropy_penalty(scales, torch.ones(1, 1, dtype=torch.bool), 4.0).backward()
    grad = scales.grad[0, 0]
    assert grad[0] < 0 and grad[2] > 0 and grad[1] == 0  # grow the thin axis, shrink the long one


def test_bad_anisotropy_settings_are_refused_when_the_config_is_built():
    with pytest.raises(ValueError, match="aniso_ratio"):
        anisotropy_penalty(torch.ones(1, 1, 3), torch.ones(1, 1, dtype=torch.bool), 0.5)
    with pytest.raises(ValueError, match="aniso_ratio"):
        PretrainLossConfig(aniso=0.01, aniso_ratio=0.5)
    with pytest.raises(ValueError, match="loss.aniso is a weight"):
        PretrainLossConfig(aniso=-1.0)


def test_pretrain_losses_add_the_weighted_anisotropy_term():
    b, t, h, w, n = 2, 3, 4, 4, 5
    gen = torch.Generator().manual_seed(0)
    rgb, alpha = torch.rand(b, t, h, w, 3, generator=gen), torch.rand(b, t, h, w, 1, generator=gen)
    target, mask = torch.rand(b, t, 3, h, w, generator=gen), torch.rand(b, t, 1, h, w, generator=gen)
    posterior = PhysicsPosterior(
        torch.randn(b, 15, generator=gen), torch.zeros(b), torch.zeros(b), torch.zeros(b), torch.zeros(b)
    )
    labels = (torch.tensor([0, 3]), torch.tensor([5.0, 6.0]), torch.tensor([0.3, 0.4]))
    scales = 0.01 + torch.rand(b, n, 3, generator=gen)
    valid = torch.ones(b, n, dtype=torch.bool)
    off = pretrain_losses(PretrainLossConfig(), rgb, alpha, target, mask, posterior, *labels)
    on = pretrain_losses(
        PretrainLossConfig(aniso=0.5),
        rgb,
        alpha,
        target,
        mask,
        posterior,
        *labels,
        scales=scales,
        valid=valid,
    )
    assert "aniso" not in off
    expected = off["loss"] + 0.5 * anisotropy_penalty(scales, valid, 4.0)
    assert on["loss"].item() == pytest.approx(expected.item(), rel=1e-6)
    with pytest.raises(ValueError, match="scales"):
        pretrain_losses(PretrainLossConfig(aniso=0.5), rgb, alpha, target, mask, posterior, *labels)


def test_surface_distance_is_the_mean_distance_to_the_nearest_true_point():
    from physgm.train.losses import surface_distance

    grid = torch.stack(torch.meshgrid(torch.arange(4.0), torch.arange(4.0), indexing="ij"), -1).reshape(-1, 2)
    plane = torch.cat([grid, torch.zeros(16, 1)], dim=1)  # the true surface: z = 0, points 1 apart
    means = torch.stack([plane, plane + torch.tensor([0.0, 0.0, 0.25])])  # on it, and 0.25 above
    valid = torch.ones(2, 16, dtype=torch.bool)
    valid[1, 8:] = False
    points = torch.stack([plane, plane])
    known = torch.tensor([True, True])
    assert surface_distance(means, valid, points, known, 100).item() == pytest.approx(0.125)
    # an asset without ground truth does not count; nor do centres beyond max_gaussians
    one = torch.tensor([False, True])
    assert surface_distance(means, valid, points, one, 100).item() == pytest.approx(0.25)
    assert surface_distance(means, valid, points, known, 3).item() == pytest.approx(0.125)
    with pytest.raises(ValueError, match="data.surface_points"):
        surface_distance(means, valid, points, torch.tensor([False, False]), 100)


def test_the_surface_term_pulls_the_centres_onto_the_surface():
    from physgm.train.losses import surface_distance

    points = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    means = torch.tensor([[[0.1, 0.0, 0.3]]], requires_grad=True)
    surface_distance(means, torch.ones(1, 1, dtype=torch.bool), points, torch.tensor([True]), 10).backward()
    assert means.grad[0, 0, 2] > 0 and means.grad[0, 0, 0] > 0  # descent moves it down and towards x = 0
    with pytest.raises(ValueError, match="loss.surface is a weight"):
        PretrainLossConfig(surface=-1.0)


def test_token_anchor_is_the_relative_squared_distance_of_each_token():
    reference = torch.tensor([[[3.0, 4.0], [0.0, 2.0]]])  # [B=1, G=2, D=2], |t_ref|^2 = 25 and 4
    tokens = torch.tensor([[[3.0, 5.0], [0.0, 2.0]]])  # the first token 1 away, the second exact
    assert token_anchor(tokens, tokens).item() == 0.0
    assert token_anchor(tokens, reference).item() == pytest.approx((1 / 25 + 0) / 2)
    with pytest.raises(ValueError, match="loss.anchor"):
        PretrainLossConfig(anchor=-1.0)
