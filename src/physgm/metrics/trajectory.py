"""Trajectory distance between a simulated clip and a reference video (the paper's DPO ranking).

Recipe: segment the plain background, track points from the reference's first frame in both clips,
normalise positions by the object's first-frame bounding box, find the landing frame of each clip
(the first frame where the lowest tracked point stops descending), align the post-landing phases
in time and subtract each clip's position at landing, then average the point distances.
Distances are in units of the object's first-frame bounding-box size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physgm.metrics.tracking import LucasKanadeTracker, PointTracker, Tracks, background_mask, select_queries


@dataclass
class BoundingBox:
    """Axis-aligned pixel box of the object in one frame."""

    x0: float
    y0: float
    size: float  # the larger side, pixels; positions are divided by it (isotropic)

    @staticmethod
    def of_mask(mask: np.ndarray) -> BoundingBox:
        ys, xs = np.nonzero(mask)
        if len(xs) == 0:
            raise ValueError("the object mask of the first frame is empty: no object to measure")
        return BoundingBox(
            float(xs.min()), float(ys.min()), float(max(xs.max() - xs.min(), ys.max() - ys.min(), 1) + 1)
        )

    def normalise(self, xy: np.ndarray) -> np.ndarray:
        """Pixel positions [..., 2] to box units."""
        return (xy - np.array([self.x0, self.y0], np.float32)) / self.size

    def denormalise(self, uv: np.ndarray) -> np.ndarray:
        return uv * self.size + np.array([self.x0, self.y0], np.float32)


@dataclass
class TrajectoryScore:
    distance: float  # mean aligned track distance, bounding-box units
    landing_reference: int  # landing frame of the reference clip
    landing_candidate: int  # landing frame of the candidate clip
    frames_compared: int
    points: int


def landing_frame(xy: np.ndarray, visible: np.ndarray, min_drop: float = 0.02, tol: float = 1e-3) -> int:
    """First frame where the lowest tracked point stops descending (image y grows downwards).

    Args:
        xy: [T, Q, 2] normalised positions.
        visible: [T, Q].
        min_drop: the point must first have descended this much (box units) for a landing to count,
            so the slow first frames of a release are not mistaken for one.
        tol: a frame-to-frame descent below this counts as stopped.
    Returns:
        The landing frame, or 0 when the object never falls (it starts at rest on the ground).
    """
    y = np.where(visible, xy[..., 1], -np.inf)
    lowest = y.max(axis=1)  # [T]
    lowest = np.maximum.accumulate(np.where(np.isfinite(lowest), lowest, -np.inf))
    for t in range(1, len(lowest) - 1):
        if lowest[t] - lowest[0] > min_drop and lowest[t + 1] - lowest[t] <= tol:
            return t
    return 0


def aligned_distance(ref: Tracks, cand: Tracks, landing_ref: int, landing_cand: int) -> tuple[float, int]:
    """Mean distance between post-landing displacements, aligned at the landing frames.

    Both track sets follow the same Q query points (normalised units). Frame ``landing_ref + k`` of
    the reference is compared with ``landing_cand + k`` of the candidate, each relative to its own
    landing position, for every k both clips have.
    """
    n = min(len(ref.xy) - landing_ref, len(cand.xy) - landing_cand)
    if n < 1:
        return float("nan"), 0
    r = ref.xy[landing_ref : landing_ref + n] - ref.xy[landing_ref]
    c = cand.xy[landing_cand : landing_cand + n] - cand.xy[landing_cand]
    both = ref.visible[landing_ref : landing_ref + n] & cand.visible[landing_cand : landing_cand + n]
    both &= ref.visible[landing_ref][None] & cand.visible[landing_cand][None]
    if not both.any():
        return float("nan"), n
    dist = np.linalg.norm(r - c, axis=-1)
    return float(dist[both].mean()), n


def score_tracks(ref: Tracks, cand: Tracks) -> TrajectoryScore:
    """Trajectory distance between two track sets of the same queries, already box-normalised."""
    lr, lc = landing_frame(ref.xy, ref.visible), landing_frame(cand.xy, cand.visible)
    dist, n = aligned_distance(ref, cand, lr, lc)
    return TrajectoryScore(dist, lr, lc, n, ref.xy.shape[1])


def score_videos(
    reference: np.ndarray,
    candidate: np.ndarray,
    tracker: PointTracker | None = None,
    background=(255, 255, 255),
    max_points: int = 64,
) -> TrajectoryScore:
    """Trajectory distance of a candidate clip to a reference clip.

    Args:
        reference: [T, H, W, 3] uint8 reference video on a plain background.
        candidate: [T', H', W', 3] uint8 simulated clip from the same camera.
        tracker: point tracker (default: OpenCV pyramidal Lucas-Kanade).
    """
    tracker = tracker or LucasKanadeTracker()
    ref_mask = background_mask(reference[:1], background)[0]
    cand_mask = background_mask(candidate[:1], background)[0]
    box_ref, box_cand = BoundingBox.of_mask(ref_mask), BoundingBox.of_mask(cand_mask)
    queries_ref = select_queries(reference[0], ref_mask, max_points)
    # The same material points in the candidate: map the queries through the two first-frame boxes.
    queries_cand = box_cand.denormalise(box_ref.normalise(queries_ref))
    ref_tracks = tracker(reference, queries_ref)
    cand_tracks = tracker(candidate, queries_cand)
    ref_n = Tracks(box_ref.normalise(ref_tracks.xy), ref_tracks.visible)
    cand_n = Tracks(box_cand.normalise(cand_tracks.xy), cand_tracks.visible)
    return score_tracks(ref_n, cand_n)
