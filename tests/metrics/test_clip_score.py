"""The rollouts' clip score: zero for the same clip, and it orders squash and rebound the way physics does."""

from __future__ import annotations

import numpy as np
import pytest

from physgm.metrics.clip_score import ScoreConfig, moment_profile, score_clip, silhouette_distance, soft_alpha
from physgm.metrics.perceptual import perceptual_distance


def drop_clip(squash: float, rebound: float, frames: int = 16, size: int = 64) -> np.ndarray:
    """A textured block falls, lands at frame 6, squashes by ``squash`` (fraction of its height, widening
    to keep its area) for 3 frames, then rebounds ``rebound`` block heights and settles."""
    rng = np.random.default_rng(0)
    tex = rng.integers(0, 200, (4, 4, 3)).repeat(4, 0).repeat(4, 1).astype(np.uint8)  # 16 x 16 px
    out = np.full((frames, size, size, 3), 255, np.uint8)
    ground = 56
    for t in range(frames):
        h, w, lift = 16.0, 16.0, 0.0
        if t < 6:
            lift = 30.0 * (1 - (t / 6) ** 2)
        elif t < 9:
            h = 16.0 * (1 - squash)
            w = 256.0 / h
        elif t < 13:
            lift = 16.0 * rebound * np.sin(np.pi * (t - 9) / 4)
        hi, wi = max(round(h), 1), max(round(w), 1)
        block = tex[np.linspace(0, 15, hi).astype(int)][:, np.linspace(0, 15, wi).astype(int)]
        y1 = int(round(ground - lift))
        x0 = 32 - wi // 2
        out[t, y1 - hi : y1, x0 : x0 + wi] = block
    return out


def test_same_clip_scores_zero_and_every_term_is_reported():
    ref = drop_clip(0.3, 0.5)
    score = score_clip(ref, ref.copy())
    assert score.value == pytest.approx(0.0, abs=1e-9)
    assert set(score.terms) == {"tracks", "profile", "silhouette"}
    assert perceptual_distance(ref, ref.copy()) == pytest.approx(0.0, abs=1e-9)


def test_profile_and_silhouette_grow_with_the_squash_and_rebound_mismatch():
    ref = drop_clip(0.3, 0.5)
    squash = [score_clip(ref, drop_clip(s, 0.5)).terms for s in (0.3, 0.2, 0.1, 0.0)]
    assert [t["profile"] for t in squash] == sorted(t["profile"] for t in squash)
    assert squash[0]["profile"] == 0.0 and squash[-1]["profile"] > 0.01
    assert squash[-1]["silhouette"] > squash[0]["silhouette"] + 0.02
    rebound = [score_clip(ref, drop_clip(0.3, r)).value for r in (0.5, 0.25, 0.0)]
    assert rebound[0] < rebound[1] < rebound[2]
    # Perceptually, a rigid block is further from the squashing reference than a near-copy.
    assert perceptual_distance(ref, drop_clip(0.0, 0.0)) > perceptual_distance(ref, drop_clip(0.25, 0.5)) > 0


def test_profile_is_relative_to_the_first_frame_so_scale_and_offset_cancel():
    ref = drop_clip(0.3, 0.5)
    big = np.repeat(np.repeat(ref, 2, 1), 2, 2)  # the same clip at twice the size
    shifted = np.roll(ref, (3, -5), axis=(1, 2))  # and moved in the image
    profile = moment_profile(soft_alpha(ref))
    assert np.abs(profile).max() > 0.5  # it falls more than half its size
    np.testing.assert_allclose(moment_profile(soft_alpha(big)), profile, atol=0.02)
    np.testing.assert_allclose(moment_profile(soft_alpha(shifted)), profile, atol=1e-6)
    masks = (ref < 250).any(-1)
    assert silhouette_distance(masks, np.repeat(np.repeat(masks, 2, 1), 2, 2)) < 0.1


def test_profile_sees_sub_pixel_motion():
    """An anti-aliased edge a quarter pixel further moves the moment profile; whole-pixel masks would not."""
    a = np.full((2, 32, 32, 3), 255, np.uint8)
    a[:, 10:20, 10:20] = 0
    b = a.copy()
    b[1, 20, 10:20] = 191  # frame 1: a quarter-pixel deeper bottom edge (coverage 0.25)
    assert moment_profile(soft_alpha(b))[1, 1] > 0.005 and moment_profile(soft_alpha(a))[1, 1] == 0.0


def test_weights_select_the_terms():
    ref, cand = drop_clip(0.3, 0.5), drop_clip(0.0, 0.0)
    tracks_only = score_clip(ref, cand, ScoreConfig(tracks=1.0, profile=0.0, silhouette=0.0))
    full = score_clip(ref, cand)
    assert tracks_only.value == pytest.approx(full.terms["tracks"])
    assert np.isnan(tracks_only.terms["profile"])
    assert full.value == pytest.approx(
        full.terms["tracks"] + full.terms["profile"] + 0.5 * full.terms["silhouette"]
    )
    with pytest.raises(ValueError, match="score weights"):
        ScoreConfig(tracks=0.0, profile=0.0, silhouette=0.0)
