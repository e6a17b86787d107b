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
