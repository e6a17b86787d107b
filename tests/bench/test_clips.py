"""``python -m physgm.bench clips``: projected distances between run folders, checked by hand."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from physgm.bench import clips
from physgm.view.sequence import SEQUENCE_FILE, GaussianSequence, StoredFrames

FOV = math.radians(60.0)
RES = 256
FOCAL = 0.5 * RES / math.tan(0.5 * FOV)  # px per (m / m of depth)


def _sequence(means: np.ndarray, n_frames: int) -> GaussianSequence:
    """Gaussians seen by a camera at the origin looking along +z (OpenCV: the identity pose)."""
    s, n, _ = means.shape
    return GaussianSequence(
        colors=np.full((n, 3), 0.5, np.float32),
        opacities=np.ones(n, np.float32),
        motion=StoredFrames(
            means=means.astype(np.float32),
            covs=np.tile(np.array([1e-4, 0, 0, 1e-4, 0, 1e-4], np.float32), (s, n, 1)),
        ),
        n_frames=n_frames,
        fps=25.0,
        camera_c2w=np.eye(4),
        camera_fov_y=FOV,
        ground=None,
    )


def _still(n_frames: int = 4) -> GaussianSequence:
    start = np.array([[0.0, 0.0, 2.0], [0.1, -0.1, 4.0]])
    return _sequence(np.repeat(start[None], n_frames, 0), n_frames)


def test_distances_are_the_projected_shifts():
    ref = _still()
    moved = ref.motion.means.copy()
    moved[2:, 0, 0] += 0.02  # the first Gaussian (depth 2 m) 2 cm to the right from frame 2 on
    run = _sequence(moved, 4)
    px = FOCAL * 0.02 / 2.0
    got = clips.compare(ref, run, RES)
    assert got["error_px_largest"] == pytest.approx(px, rel=1e-5)
    assert got["error_px_worst_frame"] == pytest.approx(px / 2, rel=1e-5)  # one of two Gaussians
    assert got["error_px"] == pytest.approx(px / 2 * 2 / 4, rel=1e-5)  # two of four frames


def test_a_clip_at_rest_repeats_its_last_stored_frame():
    ref = _still()
    moved = ref.motion.means[:2].copy()
    moved[1, 1, 1] += 0.04  # stored frames 0 and 1; frames 2 and 3 repeat frame 1
    run = _sequence(moved, 4)
    px = FOCAL * 0.04 / 4.0
    got = clips.compare(ref, run, RES)
    assert got["error_px"] == pytest.approx(px / 2 * 3 / 4, rel=1e-5)
    assert clips.tail_motion(run, RES, 2) == 0.0  # no motion after the last stored frame
    assert clips.tail_motion(run, RES, 3) == pytest.approx(px, rel=1e-5)


def test_clips_of_different_inputs_are_refused():
    ref = _still()
    other = _sequence(ref.motion.means[:, :1], 4)
    with pytest.raises(ValueError, match="same input"):
        clips.compare(ref, other, RES)
    with pytest.raises(ValueError, match="output.frames"):
        clips.compare(ref, _still(5), RES)
    behind = ref.motion.means.copy()
    behind[:, 1, 2] = -1.0  # the second Gaussian behind the camera: no pixel to compare
    with pytest.raises(ValueError, match="behind the camera"):
        clips.compare(ref, _sequence(behind, 4), RES)


def test_main_reads_run_folders(tmp_path, capsys):
    ref_dir, run_dir = tmp_path / "ref", tmp_path / "run"
    for folder, shift in ((ref_dir, 0.0), (run_dir, 0.02)):
        folder.mkdir()
        seq = _still()
        seq.motion.means[:, 0, 0] += shift
        seq.save(folder / SEQUENCE_FILE)
        report = {"output": {"resolution": RES}, "seconds": {"simulate": 1.5}, "runs": [{"substeps": 10}]}
        (folder / "report.json").write_text(json.dumps(report))
    out = clips.main([str(ref_dir), str(run_dir)])
    assert json.loads(capsys.readouterr().out) == out
    row = out["clips"][1]
    assert row["error_px_largest"] == pytest.approx(FOCAL * 0.02 / 2.0, rel=1e-5)
    assert (row["seconds_simulate"], row["substeps"]) == (1.5, 10)
    with pytest.raises(SystemExit, match="no gaussians_t.npz"):
        clips.main([str(ref_dir), str(tmp_path)])
