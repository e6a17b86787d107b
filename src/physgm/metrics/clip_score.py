"""How far a simulated drop clip is from its reference video: tracks plus what the tracks miss.

The paper's trajectory distance (``physgm.metrics.trajectory``: tracked points, box-normalised,
aligned at landing) compares motion *after* landing relative to the landing position. The DPO
landscape (``python -m physgm.bench dpo-landscape``) showed it flat on the stiff side: a stiffer
candidate squashes less and rebounds differently, and neither shows much in landing-aligned
tracks. Two silhouette terms see it, frame by frame from the release (free fall does not depend
on E, so the clips need no alignment before the impact):

- ``profile``: centroid and spread (x and y) of the object's coverage, each relative to the
  clip's own first frame and in units of its size: rebound height and timing (centroid y),
  squash and spread during contact (the spreads). Moments of an anti-aliased coverage move with
  sub-pixel motion, where mask edges move in whole pixels (one pixel is 0.03 box units on a
  64 px render, about what a quarter decade of E changes);
- ``silhouette``: 1 - IoU of the two masks per frame, the candidate's mapped into the
  reference's box frame through the two first-frame boxes (shape over time).

Every term is in box units or a fraction, so a shape mismatch of the model's own Gaussians adds a
near-constant offset rather than moving the minimum.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physgm.metrics.tracking import background_mask
from physgm.metrics.trajectory import BoundingBox, score_videos


@dataclass
class ScoreConfig:
    """Weights of the clip score's terms (``stage.rollout.sim.score``); all-zero but tracks is the paper's."""

    tracks: float = 1.0  # landing-aligned track distance (the paper's recipe), box units
    profile: float = 1.0  # centroid and spread trajectories from the release, box units
    silhouette: float = 0.5  # 1 - IoU of box-aligned masks, averaged over frames

    def __post_init__(self) -> None:
        w = (self.tracks, self.profile, self.silhouette)
        if min(w) < 0 or sum(w) <= 0:
            raise ValueError(f"score weights must be >= 0 with a positive sum, got {w}")


@dataclass
class ClipScore:
    value: float  # weighted sum of the terms (nan when a weighted term is nan)
    terms: dict[str, float]  # tracks, profile, silhouette


def soft_alpha(frames: np.ndarray, background=(255, 255, 255), full: float = 48.0) -> np.ndarray:  # [T, H, W]
    """Object coverage per pixel in [0, 1]: the largest channel difference to the background over ``full``.

    Anti-aliased edge pixels come out fractional, so moments of it move smoothly with sub-pixel motion.
    """
    diff = np.abs(frames.astype(np.float32) - np.asarray(background, np.float32)).max(-1)
    return np.clip(diff / full, 0.0, 1.0)


def moment_profile(alpha: np.ndarray) -> np.ndarray:  # [T, 4] box units
    """Centroid (x, y) and spread (std x, std y) of each frame's coverage [T, H, W], relative to the
    first frame and divided by the first frame's size (the square root of its covered area)."""
    t, h, w = alpha.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    mass = alpha.sum((1, 2)).astype(np.float64)
    out = np.full((t, 4), np.nan)
    ok = mass > 0
    if not ok[0]:
        return out
    a = alpha[ok].astype(np.float64)
    m = mass[ok][:, None, None]
    cx, cy = (a * xs).sum((1, 2)) / m[:, 0, 0], (a * ys).sum((1, 2)) / m[:, 0, 0]
    sx = np.sqrt((a * (xs - cx[:, None, None]) ** 2).sum((1, 2)) / m[:, 0, 0])
    sy = np.sqrt((a * (ys - cy[:, None, None]) ** 2).sum((1, 2)) / m[:, 0, 0])
    out[ok] = np.stack([cx, cy, sx, sy], -1)
    return (out - out[0]) / np.sqrt(mass[0])


def profile_distance(ref_alpha: np.ndarray, cand_alpha: np.ndarray) -> float:
    """Mean |difference| of the two clips' moment profiles over the frames both have (box units)."""
    n = min(len(ref_alpha), len(cand_alpha))
    diff = np.abs(moment_profile(ref_alpha[:n]) - moment_profile(cand_alpha[:n]))
    return float(np.nanmean(diff)) if np.isfinite(diff).any() else float("nan")


def silhouette_distance(ref_masks: np.ndarray, cand_masks: np.ndarray) -> float:
    """1 - mean IoU of the masks, the candidate's sampled in the reference's first-frame box frame."""
    n = min(len(ref_masks), len(cand_masks))
    box_ref, box_cand = BoundingBox.of_mask(ref_masks[0]), BoundingBox.of_mask(cand_masks[0])
    h, w = ref_masks.shape[1:]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    xy = box_cand.denormalise(box_ref.normalise(np.stack([xs, ys], -1) + 0.5)) - 0.5
    ch, cw = cand_masks.shape[1:]
    u = np.clip(np.rint(xy[..., 0]), 0, cw - 1).astype(int)
    v = np.clip(np.rint(xy[..., 1]), 0, ch - 1).astype(int)
    inside = (xy[..., 0] > -0.5) & (xy[..., 0] < cw - 0.5) & (xy[..., 1] > -0.5) & (xy[..., 1] < ch - 0.5)
    ious = []
    for t in range(n):
        cand = cand_masks[t][v, u] & inside
        union = (ref_masks[t] | cand).sum()
        if union:
            ious.append((ref_masks[t] & cand).sum() / union)
    return float(1.0 - np.mean(ious)) if ious else float("nan")


def score_clip(
    reference: np.ndarray,  # [T, H, W, 3] uint8, plain background
    candidate: np.ndarray,  # [T', H', W', 3] uint8, the same camera
    config: ScoreConfig | None = None,
    background=(255, 255, 255),
) -> ClipScore:
    """The weighted clip score of ``candidate`` against ``reference`` (lower is closer)."""
    cfg = config or ScoreConfig()
    terms = {"tracks": float("nan"), "profile": float("nan"), "silhouette": float("nan")}
    if cfg.tracks > 0:
        terms["tracks"] = score_videos(reference, candidate, background=background).distance
    if cfg.profile > 0 or cfg.silhouette > 0:
        ref_masks, cand_masks = background_mask(reference, background), background_mask(candidate, background)
        if not cand_masks[0].any() or not ref_masks[0].any():
            raise ValueError("the object mask of the first frame is empty: no object to measure")
        if cfg.profile > 0:
            terms["profile"] = profile_distance(
                soft_alpha(reference, background), soft_alpha(candidate, background)
            )
        if cfg.silhouette > 0:
            terms["silhouette"] = silhouette_distance(ref_masks, cand_masks)
    weights = {"tracks": cfg.tracks, "profile": cfg.profile, "silhouette": cfg.silhouette}
    value = sum(w * terms[k] for k, w in weights.items() if w > 0)
    return ClipScore(float(value), terms)
