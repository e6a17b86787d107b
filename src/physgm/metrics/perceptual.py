"""A perceptual distance between two clips: deep-feature differences of a frozen ImageNet network.

LPIPS's recipe without its learned per-channel weights (the "baseline" variant of Zhang et al.
2018): each of the frozen MobileNetV2's stride-4, -8 and -16 feature maps is normalised to unit
length per pixel over its channels, the squared differences are summed over channels, averaged
over pixels, then over levels and frames. The network is the one the CPU model already uses
(``physgm.model.cnn_encoder``, weights from a local package file), so nothing is downloaded; LPIPS
itself needs a torchvision backbone file this project does not ship.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

_ENCODER: list = []  # one frozen encoder per process, built on first use
LEVELS = ("s4", "s8", "s16")


def _encoder():
    if not _ENCODER:
        from physgm.model.cnn_encoder import MobileNetEncoder

        _ENCODER.append(MobileNetEncoder())
    return _ENCODER[0]


def _features(frames: np.ndarray, size: int) -> list[torch.Tensor]:  # per level [T, C, h, w]
    x = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).float() / 255.0
    if x.shape[-1] != size or x.shape[-2] != size:
        x = F.interpolate(x, size=(size, size), mode="area")
    feats = _encoder().encode(x)
    return [F.normalize(getattr(feats, name), dim=1, eps=1e-8) for name in LEVELS]


def perceptual_distance(
    reference: np.ndarray,  # [T, H, W, 3] uint8
    candidate: np.ndarray,  # [T', H', W', 3] uint8 (resized to the common size)
    size: int = 64,  # px, square; a multiple of 32
) -> float:
    """Mean feature distance over the frames both clips have (0: identical; about 0.1-1 for unlike images)."""
    n = min(len(reference), len(candidate))
    with torch.no_grad():
        ref, cand = _features(reference[:n], size), _features(candidate[:n], size)
        per_level = [((a - b) ** 2).sum(1).mean() for a, b in zip(ref, cand, strict=True)]
    return float(torch.stack(per_level).mean())
