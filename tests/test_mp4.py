"""The one mp4 encoding: deterministic bytes, a faithful round trip, and a clear refusal of bad frames."""

from __future__ import annotations

import numpy as np
import pytest

from physgm.mp4 import read_mp4, write_mp4


def _clip() -> np.ndarray:  # [T, H, W, 3] uint8: a grey ramp moving over white
    frames = np.full((10, 32, 48, 3), 255, np.uint8)
    for t in range(10):
        frames[t, 8:24, 2 + 3 * t : 14 + 3 * t] = np.linspace(40, 200, 12, dtype=np.uint8)[None, :, None]
    return frames


def test_same_frames_same_bytes_and_a_close_round_trip(tmp_path):
    frames = _clip()
    write_mp4(tmp_path / "a.mp4", frames, 25.0)
    write_mp4(tmp_path / "b.mp4", frames, 25.0)
    assert (tmp_path / "a.mp4").read_bytes() == (tmp_path / "b.mp4").read_bytes()
    back = read_mp4(tmp_path / "a.mp4")
    assert back.shape == frames.shape and back.dtype == np.uint8
    err = np.abs(back.astype(float) - frames)
    assert err.mean() < 2.0 and err.max() < 40  # CRF 18: visually lossless, chroma blurs the edges
    assert read_mp4(tmp_path / "a.mp4", n_frames=4).shape[0] == 4


def test_float_frames_are_refused_with_the_expected_layout(tmp_path):
    with pytest.raises(ValueError, match=r"uint8 \[T, H, W, 3\]"):
        write_mp4(tmp_path / "x.mp4", _clip().astype(np.float32) / 255, 25.0)
    assert not (tmp_path / "x.mp4").exists()
