"""Validation panels: inputs, predictions and targets in one picture."""

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
