"""Novel-view image metrics (torchmetrics PSNR and SSIM) and the image panels logged in validation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn
from torchmetrics import MeanMetric
from torchmetrics.functional.image import peak_signal_noise_ratio
from torchmetrics.image import StructuralSimilarityIndexMeasure


class ImageMetrics(nn.Module):
    """PSNR (dB) and SSIM over images in [0, 1], averaged per image."""

    def __init__(self) -> None:
        super().__init__()
        # The mean of per-image PSNRs. Not PeakSignalNoiseRatio(dim=...): its per-image states are lists
        # holding int64 pixel counts, and under DDP a rank without images adds an empty float32 one to the
        # gather, which gloo cannot match (the run aborted). A mean has two float sums, zero when empty.
        self.psnr = MeanMetric()
        self.ssim = StructuralSimilarityIndexMeasure(data_range=1.0)
        self.update_count = 0

    def update(self, pred: Tensor, target: Tensor) -> None:
        """Add images ``pred`` and ``target``, [N, 3, H, W]."""
        self.psnr.update(
            peak_signal_noise_ratio(
                pred.detach().float(), target.float(), data_range=1.0, reduction="none", dim=(1, 2, 3)
            )
        )
        self.ssim.update(pred.detach().float(), target.float())
        self.update_count += 1

    def compute(self) -> dict[str, Tensor]:
        return {"psnr": self.psnr.compute(), "ssim": self.ssim.compute()}

    def reset(self) -> None:
        self.psnr.reset()
        self.ssim.reset()
        self.update_count = 0


def panel_image(inputs: Tensor, pred: Tensor, target: Tensor) -> np.ndarray:
    """One uint8 picture: input views on the first row, predictions on the second, targets on the third.

    Args:
        inputs: [V, 3, Hi, Wi] (resized to H x W); pred, target: [T, 3, H, W], all in [0, 1].
    """
    t, _, h, w = target.shape
    if inputs.shape[-2:] != (h, w):  # inputs may be smaller than the targets (e.g. 32 px in, 64 px out)
        inputs = torch.nn.functional.interpolate(inputs.detach().float(), size=(h, w), mode="nearest")
    rows = torch.ones(3, 3, h, w * t)
    for row, images in enumerate([inputs, pred, target]):
        for i, img in enumerate(images[:t]):
            rows[row, :, :, i * w : (i + 1) * w] = img.detach().float().cpu()[:, :h, :w]
    grid = torch.cat(list(rows), dim=1)  # [3, 3H, TW]
    return (grid.clamp(0, 1).permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)


def save_panel(module, inputs: Tensor, pred: Tensor, target: Tensor, tag: str) -> Path | None:
    """Write a validation panel as PNG in the run folder and hand it to image-capable loggers."""
    import imageio.v3 as iio

    picture = panel_image(inputs, pred, target)
    trainer = module.trainer
    folder = Path(trainer.default_root_dir) / "panels"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{tag}_step{trainer.global_step:07d}.png"
    iio.imwrite(path, picture)
    for logger in trainer.loggers:
        experiment = getattr(logger, "experiment", None)
        if hasattr(experiment, "add_image"):  # TensorBoard
            experiment.add_image(tag, picture, trainer.global_step, dataformats="HWC")
        elif hasattr(logger, "log_image"):  # wandb
            logger.log_image(key=tag, images=[picture], step=trainer.global_step)
    return path
