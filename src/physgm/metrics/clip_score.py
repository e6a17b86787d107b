"""How far a simulated drop clip is from its reference video: tracks plus what the tracks miss.

The paper's trajectory distance (``physgm.metrics.trajectory``: tracked points, box-normalised,
aligned at landing) compares motion *after* landing relative to the landing position. The DPO
landscape (``python -m physgm.bench dpo-landscape``) showed it flat on the stiff side: a stiffer
candidate squashes less and rebounds differently, and neither shows much in landing-aligned
tracks. Two silhouette terms see it, frame by frame from the release (free fall does not depend
on E, so the clips need no alignment before the impact):

- ``profile``: the top, bottom, left and right edges of the object mask, each relative to the
  clip's own first-frame box and in units of its size: rebound height and timing (top and
  bottom), squash and spread during contact (all four);
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
    profile: float = 1.0  # mask edge trajectories from the release, box units
    silhouette: float = 0.5  # 1 - IoU of box-aligned masks, averaged over frames

    def __post_init__(self) -> None:
        w = (self.tracks, self.profile, self.silhouette)
        if min(w) < 0 or sum(w) <= 0:
            raise ValueError(f"score weights must be >= 0 with a positive sum, got {w}")


@dataclass
class ClipScore:
    value: float  # weighted sum of the terms (nan when a weighted term is nan)
    terms: dict[str, float]  # tracks, profile, silhouette


def mask_edges(masks: np.ndarray) -> np.ndarray:  # [T, 4] top, bottom, left, right (pixels; nan: empty)
    """Extreme rows and columns of each frame's mask [T, H, W] bool."""
    out = np.full((len(masks), 4), np.nan)
    for t, m in enumerate(masks):
        rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
        if len(rows):
            out[t] = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    return out


def edge_profile(masks: np.ndarray) -> np.ndarray:  # [T, 4] box units
    """Mask edges relative to the first frame's, divided by the first frame's box size."""
    edges = mask_edges(masks)
    size = max(edges[0, 1] - edges[0, 0], edges[0, 3] - edges[0, 2], 1.0)
    return (edges - edges[0]) / size


def profile_distance(ref_masks: np.ndarray, cand_masks: np.ndarray) -> float:
    """Mean |difference| of the two clips' edge profiles over frames both have (box units)."""
    n = min(len(ref_masks), len(cand_masks))
    diff = np.abs(edge_profile(ref_masks[:n]) - edge_profile(cand_masks[:n]))
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


def match_size(frames: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``frames`` [T, H, W, 3] uint8 area-resampled to ``size`` (h, w) when larger, else unchanged."""
    import cv2

    h, w = size
    if frames.shape[1:3] == (h, w) or frames.shape[1] < h or frames.shape[2] < w:
        return frames
    return np.stack([cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA) for f in frames])


def score_clip(
    reference: np.ndarray,  # [T, H, W, 3] uint8, plain background
    candidate: np.ndarray,  # [T', H', W', 3] uint8, the same camera
    config: ScoreConfig | None = None,
    background=(255, 255, 255),
) -> ClipScore:
    """The weighted clip score of ``candidate`` against ``reference`` (lower is closer).

    A reference larger than the candidate is first area-resampled to the candidate's size, so both
    masks sit on the same pixel grid: a 128 px reference against a 64 px render otherwise differs by
    a pixel of edge quantisation everywhere (0.05 box units on a 20 px object) whatever the physics.
    """
    cfg = config or ScoreConfig()
    reference = match_size(reference, candidate.shape[1:3])
    terms = {"tracks": float("nan"), "profile": float("nan"), "silhouette": float("nan")}
    if cfg.tracks > 0:
        terms["tracks"] = score_videos(reference, candidate, background=background).distance
    if cfg.profile > 0 or cfg.silhouette > 0:
        ref_masks, cand_masks = background_mask(reference, background), background_mask(candidate, background)
        if not cand_masks[0].any() or not ref_masks[0].any():
            raise ValueError("the object mask of the first frame is empty: no object to measure")
        if cfg.profile > 0:
            terms["profile"] = profile_distance(ref_masks, cand_masks)
        if cfg.silhouette > 0:
            terms["silhouette"] = silhouette_distance(ref_masks, cand_masks)
    weights = {"tracks": cfg.tracks, "profile": cfg.profile, "silhouette": cfg.silhouette}
    value = sum(w * terms[k] for k, w in weights.items() if w > 0)
    return ClipScore(float(value), terms)
