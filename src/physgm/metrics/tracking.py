"""Object masks on plain backgrounds and point tracks through a video.

The tracker is an interface (``PointTracker``) so a user can swap OpenCV's pyramidal Lucas-Kanade
for CoTracker or another learned tracker; the trajectory metric only needs ``Tracks``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass
class Tracks:
    """Q points tracked through T frames.

    Attributes:
        xy: [T, Q, 2] pixel positions (x right, y down).
        visible: [T, Q] True where the tracker still follows the point.
    """

    xy: np.ndarray  # [T, Q, 2]
    visible: np.ndarray  # [T, Q]

    def __post_init__(self) -> None:
        if self.xy.ndim != 3 or self.xy.shape[-1] != 2 or self.visible.shape != self.xy.shape[:2]:
            raise ValueError(
                f"Tracks need xy [T, Q, 2] and visible [T, Q], got {self.xy.shape} and {self.visible.shape}"
            )


class PointTracker(Protocol):
    def __call__(self, frames: np.ndarray, queries: np.ndarray) -> Tracks:
        """Track ``queries`` [Q, 2] (pixels in frame 0) through ``frames`` [T, H, W, 3] uint8."""


def background_mask(frames: np.ndarray, background=(255, 255, 255), threshold: float = 12.0) -> np.ndarray:
    """Object masks [T, H, W] bool by segmenting a plain background of known colour.

    A pixel belongs to the object when its largest channel difference to the background exceeds
    ``threshold`` (0-255 scale); small speckles are removed with a 3x3 opening.
    """
    import cv2

    frames = np.asarray(frames)
    if frames.ndim == 3:
        frames = frames[None]
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"frames must have shape [T, H, W, 3], got {frames.shape}")
    diff = np.abs(frames.astype(np.int16) - np.asarray(background, dtype=np.int16)).max(-1)
    masks = (diff > threshold).astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    return np.stack([cv2.morphologyEx(m, cv2.MORPH_OPEN, kernel) for m in masks]).astype(bool)


def select_queries(
    frame: np.ndarray, mask: np.ndarray, max_points: int = 64, min_distance: int = 3
) -> np.ndarray:
    """Good features to track inside ``mask`` of one frame, [Q, 2] pixels.

    Falls back to a regular grid over the mask when the object has too little texture for corners.
    """
    import cv2

    grey = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY)
    mask_u8 = mask.astype(np.uint8) * 255
    corners = cv2.goodFeaturesToTrack(
        grey, maxCorners=max_points, qualityLevel=0.01, minDistance=min_distance, mask=mask_u8
    )
    points = np.zeros((0, 2), np.float32) if corners is None else corners.reshape(-1, 2)
    if len(points) < max_points // 2:
        ys, xs = np.nonzero(mask)
        if len(xs) == 0:
            raise ValueError("select_queries: the mask is empty; no object to track in the first frame")
        step = max(1, int(np.sqrt(len(xs) / max_points)))
        grid = np.stack([xs, ys], -1)[(xs % step == 0) & (ys % step == 0)].astype(np.float32)
        points = np.concatenate([points, grid[: max_points - len(points)]])
    return points.astype(np.float32)


@dataclass
class LucasKanadeTracker:
    """OpenCV pyramidal Lucas-Kanade, frame to frame, with a forward-backward consistency check."""

    window: int = 15  # search window side, pixels
    levels: int = 3  # pyramid levels
    max_fb_error: float = 1.5  # forward-backward disagreement above which a point is lost, pixels

    def __call__(self, frames: np.ndarray, queries: np.ndarray) -> Tracks:
        import cv2

        frames = np.asarray(frames)
        t, q = frames.shape[0], queries.shape[0]
        grey = [cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2GRAY) for f in frames]
        xy = np.zeros((t, q, 2), np.float32)
        visible = np.zeros((t, q), bool)
        xy[0], visible[0] = queries, True
        params = dict(
            winSize=(self.window, self.window),
            maxLevel=self.levels,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        )
        for i in range(1, t):
            prev = xy[i - 1].reshape(-1, 1, 2)
            nxt, ok, _ = cv2.calcOpticalFlowPyrLK(grey[i - 1], grey[i], prev, None, **params)
            back, ok_b, _ = cv2.calcOpticalFlowPyrLK(grey[i], grey[i - 1], nxt, None, **params)
            fb = np.linalg.norm(back.reshape(-1, 2) - xy[i - 1], axis=-1)
            good = (
                visible[i - 1]
                & ok.reshape(-1).astype(bool)
                & ok_b.reshape(-1).astype(bool)
                & (fb < self.max_fb_error)
            )
            # A lost point stays where it was last seen, so later frames do not jump; it is marked invisible.
            xy[i] = np.where(good[:, None], nxt.reshape(-1, 2), xy[i - 1])
            visible[i] = good
        return Tracks(xy, visible)
