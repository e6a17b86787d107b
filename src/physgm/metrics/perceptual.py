"""A perceptual distance from deep-feature differences of a frozen ImageNet network.

LPIPS's recipe without its learned per-channel weights (the "baseline" variant of Zhang et al.
2018): each of the frozen MobileNetV2's stride-4, -8 and -16 feature maps is normalised to unit
length per pixel over its channels, the squared differences are summed over channels, averaged
over pixels, then over levels. The network is the one the CPU model already uses
(``physgm.model.cnn_encoder``, weights from a local package file), so nothing is downloaded; LPIPS
itself needs a torchvision backbone file this project does not ship.

Two uses: ``perceptual_distance`` between two clips (the DPO ablation's second metric), and
``FeatureDistance``, differentiable in its first argument, as the training loss's LPIPS term
(``stage.loss.lpips_net=mobilenet``, through ``physgm.metrics.lpips.load_lpips``).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

LEVELS = ("s4", "s8", "s16")
STRIDE = 16  # the deepest level's: image sizes must be its multiples


class FeatureDistance(nn.Module):
    """Per-image distance between images [N, 3, H, W] (H, W multiples of 16), frozen weights.

    Called as ``lpips.LPIPS`` is: images in [-1, 1], or in [0, 1] with ``normalize=True``.

    Args:
        weights: a MobileNetV2 state dict file; default: the one the weights package ships.
    """

    def __init__(self, weights: str | None = None) -> None:
        super().__init__()
        from physgm.model.cnn_encoder import MobileNetEncoder

        self.encoder = MobileNetEncoder(weights)

    def forward(self, pred: Tensor, target: Tensor, normalize: bool = False) -> Tensor:  # [N]
        if pred.shape != target.shape:
            raise ValueError(
                f"images to compare must have one shape, got {tuple(pred.shape)} and {tuple(target.shape)}"
            )
        h, w = pred.shape[-2:]
        if h % STRIDE or w % STRIDE:
            raise ValueError(f"image size {h}x{w} must be a multiple of {STRIDE} for the perceptual distance")
        if not normalize:
            pred, target = (pred + 1) / 2, (target + 1) / 2
        a = self.encoder.pyramid(pred, last=LEVELS[-1])
        with torch.no_grad():
            b = self.encoder.pyramid(target, last=LEVELS[-1])
        unit = {n: (F.normalize(a[n], dim=1, eps=1e-8), F.normalize(b[n], dim=1, eps=1e-8)) for n in LEVELS}
        per_level = [((x - y) ** 2).sum(1).mean((1, 2)) for x, y in unit.values()]
        return torch.stack(per_level).mean(0)


_MODULE: list[FeatureDistance] = []  # one frozen network per process for the clip distance


def perceptual_distance(
    reference: np.ndarray,  # [T, H, W, 3] uint8
    candidate: np.ndarray,  # [T', H', W', 3] uint8 (resized to the common size)
    size: int = 64,  # px, square; a multiple of 16
) -> float:
    """Mean feature distance over the frames both clips have (0: identical; about 0.1-1 for unlike images)."""
    if not _MODULE:
        _MODULE.append(FeatureDistance().eval())
    n = min(len(reference), len(candidate))

    def frames(clip: np.ndarray) -> Tensor:
        x = torch.from_numpy(np.ascontiguousarray(clip[:n])).permute(0, 3, 1, 2).float() / 255.0
        return F.interpolate(x, size=(size, size), mode="area") if x.shape[-2:] != (size, size) else x

    with torch.no_grad():
        return float(_MODULE[0](frames(candidate), frames(reference), normalize=True).mean())
