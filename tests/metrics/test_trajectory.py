import numpy as np
import pytest

from physgm.metrics.tracking import LucasKanadeTracker, Tracks, background_mask, select_queries
from physgm.metrics.trajectory import BoundingBox, landing_frame, score_tracks, score_videos


def drop_tracks(t_frames=40, land=12, bounce=0.3, height=1.0, q=30, seed=0) -> np.ndarray:
    """Pixel tracks [T, Q, 2] of a unit box falling until ``land``, then a damped bounce."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(0, 1, (q, 2))  # points inside a unit box
    t = np.arange(t_frames, dtype=np.float64)
    fall = np.minimum(t, land) ** 2 / land**2 * height  # reaches `height` at the landing frame
    after = np.clip(t - land, 0, None)
    hop = (
        bounce * np.abs(np.sin(np.pi * after / 8)) * np.exp(-after / 10)
    )  # goes up (smaller y) after landing
    y = fall - hop
    return base[None] + np.stack([np.zeros_like(y), y], -1)[:, None]


def normalised(xy: np.ndarray) -> Tracks:
    lo, hi = xy[0].min(0), xy[0].max(0)
    box = BoundingBox(lo[0], lo[1], float(max(hi - lo)))
    return Tracks(box.normalise(xy.astype(np.float32)), np.ones(xy.shape[:2], bool))


def test_landing_frame_found():
    xy = drop_tracks(land=12)
    assert landing_frame(normalised(xy).xy, np.ones(xy.shape[:2], bool)) == 12
    resting = np.repeat(xy[:1], 20, 0)
    assert landing_frame(normalised(resting).xy, np.ones(resting.shape[:2], bool)) == 0


@pytest.mark.parametrize(
    "scale,offset,land_shift", [(1.0, (0, 0), 0), (2.5, (40, -13), 0), (0.6, (7, 90), 5), (1.7, (-3, 4), -4)]
)
def test_metric_recovers_scale_offset_and_landing_shift(scale, offset, land_shift):
    ref = drop_tracks(land=12) * 30 + 5
    # Same physics seen bigger, elsewhere in the image, and landing later or earlier.
    cand = drop_tracks(land=12 + land_shift, height=(12 + land_shift) ** 2 / 144) * 30 * scale + np.array(
        offset
    )
    s = score_tracks(normalised(ref), normalised(cand))
    assert (s.landing_reference, s.landing_candidate) == (12, 12 + land_shift)
    assert s.distance < 1e-5


def test_metric_separates_different_physics():
    ref = normalised(drop_tracks(bounce=0.3))
    close = score_tracks(ref, normalised(drop_tracks(bounce=0.25))).distance
    far = score_tracks(ref, normalised(drop_tracks(bounce=0.0))).distance
    assert 0 < close < far
    # Distance is in box units: a bounce of 0.3 box sizes at most gives a mean below 0.3.
    assert far < 0.3


def textured_clip(offsets, size=24, res=96, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    texture = rng.integers(0, 200, (size // 4, size // 4, 3)).repeat(4, 0).repeat(4, 1).astype(np.uint8)
    frames = np.full((len(offsets), res, res, 3), 255, np.uint8)
    for f, (dx, dy) in enumerate(offsets):
        frames[f, dy : dy + size, dx : dx + size] = texture
    return frames


def test_background_mask_and_lk_tracks_follow_known_motion():
    offsets = [(20 + t, 10 + 2 * t) for t in range(12)]
    clip = textured_clip(offsets)
    masks = background_mask(clip)
    assert masks[0, 10:34, 20:44].all() and masks[0].sum() == 24 * 24
    queries = select_queries(clip[0], masks[0], max_points=32)
    assert len(queries) >= 16 and masks[0][queries[:, 1].astype(int), queries[:, 0].astype(int)].all()
    tracks = LucasKanadeTracker()(clip, queries)
    moved = tracks.xy[-1] - tracks.xy[0]
    ok = tracks.visible[-1]
    assert ok.mean() > 0.8
    np.testing.assert_allclose(moved[ok], np.tile([[11.0, 22.0]], (ok.sum(), 1)), atol=0.5)


def test_score_videos_identical_and_shifted_clip():
    fall = [(30, min(5 + t * t // 2, 60)) for t in range(16)]
    ref = textured_clip(fall)
    assert score_videos(ref, ref).distance < 1e-3
    # The same motion 7 pixels to the right: the box normalisation removes it.
    shifted = textured_clip([(x + 7, y) for x, y in fall])
    assert score_videos(ref, shifted).distance < 0.02
    with pytest.raises(ValueError, match="empty"):
        score_videos(np.full_like(ref, 255), ref)
