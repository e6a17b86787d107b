"""Novel-view image metrics (torchmetrics PSNR and SSIM, PSNR by angle from the inputs) and the
image panels logged in validation."""

from __future__ import annotations

import math
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


class ErrorByAngle:
    """Novel views' squared error pooled by their angle from the nearest input camera.

    One view cannot show an object's far side, so its error grows with the angle a target view
    turns away from the input; this says by how much. The angle is between optical axes; a bin's
    PSNR is that of its views' mean squared error (pooled, not a mean of per-view PSNRs).
    """

    def __init__(self, bin_deg: float = 30.0) -> None:
        if not 0 < bin_deg <= 180:
            raise ValueError(f"bin_deg must be in (0, 180], got {bin_deg}")
        self.bin_deg = bin_deg
        self._sums: dict[int, list[float]] = {}  # bin index -> [summed MSE, views]

    def update(
        self,
        input_c2w: Tensor,  # [B, V, 4, 4] the input cameras
        target_c2w: Tensor,  # [B, T, 4, 4] the novel target cameras
        mse: Tensor,  # [B, T] each target view's mean squared error
    ) -> None:
        axis_in = nn.functional.normalize(input_c2w[..., :3, 2].float(), dim=-1)  # [B, V, 3]
        axis_t = nn.functional.normalize(target_c2w[..., :3, 2].float(), dim=-1)  # [B, T, 3]
        cosine = torch.einsum("btc,bvc->btv", axis_t, axis_in).amax(-1).clamp(-1.0, 1.0)  # nearest input
        degrees = torch.rad2deg(torch.acos(cosine))  # [B, T]
        last = math.ceil(180.0 / self.bin_deg) - 1  # 180 degrees belongs to the last bin
        bins = torch.clamp((degrees / self.bin_deg).floor().long(), max=last)
        for b, e in zip(bins.flatten().tolist(), mse.detach().float().flatten().tolist(), strict=True):
            total = self._sums.setdefault(b, [0.0, 0])
            total[0] += e
            total[1] += 1

    def compute(self) -> dict[str, dict[str, float]]:
        """``{"0-30": {"views": n, "psnr": dB}, ...}`` for each bin that has views, in angle order."""
        report = {}
        for b in sorted(self._sums):
            total, n = self._sums[b]
            lo, hi = b * self.bin_deg, min((b + 1) * self.bin_deg, 180.0)
            psnr = float("inf") if total == 0 else -10.0 * math.log10(total / n)
            report[f"{lo:g}-{hi:g}"] = {"views": n, "psnr": psnr}
        return report


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
