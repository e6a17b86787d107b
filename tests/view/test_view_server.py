"""The viewer's server side without a browser: what it sends for a frame, the slider, play, the camera."""

from __future__ import annotations

import time

import numpy as np
import pytest

from physgm.view.sequence import GaussianSequence, StoredFrames, matrix_to_triu

pytest.importorskip(
    "viser",
    reason="the viewer's extra is not installed (pip install -e '.[view]'; scripts/setup.sh installs it)",
)


def millimetre_sequence(frames: int = 6) -> GaussianSequence:
    """20 Gaussians of 0.3 to 1 mm (variances 1e-7 to 1e-6 m^2) drifting 1 cm per frame along +x."""
    rng = np.random.default_rng(3)
    n = 20
    s = rng.uniform(3e-4, 1e-3, (n, 3))
    covs = matrix_to_triu(np.einsum("ni,ij->nij", s**2, np.eye(3)))
    base = rng.uniform(-0.05, 0.05, (n, 3))
    means = base[None] + np.arange(frames)[:, None, None] * np.array([0.01, 0.0, 0.0])
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2] = (
        [0, 1, 0],
        [0, 0, -1],
        [-1, 0, 0],
    )  # OpenCV: right, down, forward (-x)
    c2w[:3, 3] = [0.5, 0.0, 0.0]
    motion = StoredFrames(means=means, covs=np.broadcast_to(covs, (frames, n, 6)).copy())
    return GaussianSequence(colors=rng.uniform(size=(n, 3)), opacities=np.full(n, 0.8), motion=motion,
                            n_frames=frames, fps=25.0, camera_c2w=c2w, camera_fov_y=0.7)  # fmt: skip


@pytest.fixture
def viewer():
    from physgm.view.server import SequenceViewer

    v = SequenceViewer(millimetre_sequence(), port=0, frame=0, playing=False)
    yield v
    v.close()


def test_a_frame_reaches_the_splats_in_metres_with_millimetre_detail(viewer):
    seq = viewer.sequence
    viewer.set_frame(4)
    assert viewer.frame == 4 and viewer.time_text.value == "0.160"
    splats = viewer.splats
    assert splats.scale == pytest.approx(viewer.unit)  # the node maps display units back to metres
    np.testing.assert_allclose(splats.centers * viewer.unit, seq.frame(4)[0], atol=1e-7)
    # viser stores covariances as float16; in metres these variances (1e-7..1e-6 m^2) would be
    # subnormal with 2-3 significant bits. Sent in object units they keep float16's 3 digits.
    sent = splats.covariances.astype(np.float64) * viewer.unit**2
    want = seq.frame(4)[1]
    diag = np.arange(3)
    np.testing.assert_allclose(sent[:, diag, diag], want[:, diag, diag], rtol=2e-3)
    in_metres = want[:, diag, diag].astype(np.float16).astype(np.float64)
    assert np.abs(in_metres / want[:, diag, diag] - 1).max() > 0.02  # what the unit scaling avoids
    with pytest.raises(ValueError, match="outside the clip's 6 frames"):
        viewer.set_frame(6)


def test_play_advances_and_pause_holds(viewer):
    viewer.play(True)
    deadline = time.monotonic() + 10.0
    while viewer.frame < 2 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert viewer.frame >= 2
    viewer.play(False)
    time.sleep(0.1)  # a tick already past its check may still land
    held = viewer.frame
    time.sleep(0.3)  # about 7 frames at 25 fps
    assert viewer.frame == held


def test_camera_opens_at_the_clips_camera():
    from physgm.view.server import camera_view

    c2w = millimetre_sequence().camera_c2w
    eye, look_at, up = camera_view(c2w, np.array([0.0, 0.3, 0.0]))
    np.testing.assert_allclose(eye, [0.5, 0.0, 0.0])
    # forward is the third column; the look-at point is the target's projection on it
    np.testing.assert_allclose(look_at, eye + c2w[:3, 2] * np.dot([0.0, 0.3, 0.0] - eye, c2w[:3, 2]))
    np.testing.assert_allclose(look_at, [0.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(up, [0.0, 0.0, 1.0])  # OpenCV's y points down in the image


def test_a_clip_stored_as_followed_particles_is_shown_frame_by_frame():
    """The viewer computes each frame of a clip stored as its particles' motion when it shows it."""
    from physgm.view.sequence import FollowedParticles
    from physgm.view.server import SequenceViewer

    rng = np.random.default_rng(4)
    n, p, k, frames = 50, 6, 3, 4
    x = rng.uniform(-0.05, 0.05, (p, 3)) + np.arange(frames)[:, None, None] * np.array([0.01, 0.0, 0.0])
    motion = FollowedParticles(
        rest_covs=np.tile(np.array([1e-6, 0, 0, 1e-6, 0, 1e-6], np.float32), (n, 1)),
        index=rng.integers(0, p, (n, k)).astype(np.int32),
        weight=np.full((n, k), 1.0 / k, np.float32),
        offset=rng.normal(scale=0.005, size=(n, k, 3)).astype(np.float32),
        x=x.astype(np.float32),
        F=np.broadcast_to(np.eye(3, dtype=np.float32), (frames, p, 3, 3)).copy(),
    )
    c2w = millimetre_sequence(frames).camera_c2w
    seq = GaussianSequence(colors=np.full((n, 3), 0.5), opacities=np.full(n, 0.8), motion=motion,
                           n_frames=frames, fps=25.0, camera_c2w=c2w, camera_fov_y=0.7)  # fmt: skip
    viewer = SequenceViewer(seq, port=0, frame=0, playing=False)
    try:
        viewer.set_frame(3)
        np.testing.assert_allclose(viewer.splats.centers * viewer.unit, seq.frame(3)[0], atol=1e-6)
        shift = (viewer.splats.centers * viewer.unit - seq.frame(0)[0]).mean(0)
        np.testing.assert_allclose(shift, [0.03, 0.0, 0.0], atol=1e-6)  # three frames of 1 cm along +x
    finally:
        viewer.close()
