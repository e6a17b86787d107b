"""Image metrics (PSNR, its split by angle from the inputs) and the validation panels."""

import math

import pytest
import torch


def test_panel_puts_smaller_inputs_at_the_target_size():
    from physgm.metrics.image import panel_image

    inputs = torch.zeros(1, 3, 32, 32)
    inputs[:, 0] = 1.0  # red
    pred, target = torch.full((3, 3, 64, 64), 0.5), torch.ones(3, 3, 64, 64)
    picture = panel_image(inputs, pred, target)
    assert picture.shape == (3 * 64, 3 * 64, 3)
    assert (picture[:64, :64] == [255, 0, 0]).all()  # the input, upsampled to fill its 64 px cell
    assert (picture[64:128] == 128).all() and (picture[128:] == 255).all()


def test_psnr_is_the_mean_of_per_image_psnrs_over_updates():
    gen = torch.Generator().manual_seed(0)
    target = torch.rand(5, 3, 16, 16, generator=gen)
    noise = torch.tensor([0.01, 0.03, 0.1, 0.2, 0.05]).view(5, 1, 1, 1)
    pred = (target + noise * torch.randn(5, 3, 16, 16, generator=gen)).clamp(0, 1)
    from physgm.metrics.image import ImageMetrics

    # mean of per-image PSNRs; the DDP validation needs its states to be plain float sums (train/pretrain.py)
    metrics = ImageMetrics()
    metrics.update(pred[:2], target[:2])  # batches of different sizes: each image counts once
    metrics.update(pred[2:], target[2:])
    mse = ((pred - target) ** 2).flatten(1).mean(1)
    expected = (10 * torch.log10(1.0 / mse)).mean()
    torch.testing.assert_close(metrics.compute()["psnr"], expected)
    assert metrics.update_count == 2
    metrics.reset()
    assert metrics.update_count == 0


def _camera_facing(degrees: float) -> torch.Tensor:  # [4, 4] optical axis at this azimuth
    a = torch.deg2rad(torch.tensor(degrees))
    c2w = torch.eye(4)
    c2w[:3, 2] = torch.stack([torch.cos(a), torch.sin(a), torch.tensor(0.0)])
    return c2w


def test_error_by_angle_pools_each_bin_from_the_nearest_input():
    from physgm.metrics.image import ErrorByAngle

    metric = ErrorByAngle(bin_deg=30)
    one = _camera_facing(0.0)[None, None]  # [1, 1, 4, 4]
    targets = torch.stack([_camera_facing(d) for d in (10.0, 20.0, 95.0, 180.0)])[None]
    metric.update(one, targets, torch.tensor([[0.01, 0.03, 0.1, 0.001]]))
    # two inputs: a target at 170 degrees from the first is 10 from the second
    two = torch.stack([_camera_facing(0.0), _camera_facing(180.0)])[None]
    metric.update(two, _camera_facing(170.0)[None, None], torch.tensor([[0.04]]))
    report = metric.compute()
    assert list(report) == ["0-30", "90-120", "150-180"]
    assert report["0-30"]["views"] == 3
    assert abs(report["0-30"]["psnr"] - 10 * math.log10(3 / 0.08)) < 1e-4  # pooled: mean MSE 0.08 / 3
    assert abs(report["90-120"]["psnr"] - 10.0) < 1e-4
    assert report["150-180"] == {"views": 1, "psnr": pytest.approx(30.0)}  # 180 degrees is in the last bin
