"""The 4D viewer in a real headless Chromium: the object is drawn where the clip's camera sees it,
and it moves when the time slider moves.

A red ball of 300 Gaussians falls 0.24 m in 10 frames in front of a camera 1 m away. The test
reads the ball's pixels off the page's screenshots (red, unlike anything in viser's interface)
and compares their centre with the pinhole projection of the ball's centre.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from physgm.view.browser import find_chromium

pytest.importorskip(
    "viser",
    reason="the viewer's extra is not installed (pip install -e '.[view]'; scripts/setup.sh installs it)",
)
if find_chromium() is None:
    pytest.skip("no Chromium (apt-get install chromium; .ci/run installs it in CI)",
                allow_module_level=True)  # fmt: skip

WIDTH, HEIGHT = 1000, 500  # wide: viser's control panel sits on the right, the ball in the middle
EYE = np.array([1.0, 0.0, 0.2])  # m, looking along -x at the ball's start height
TARGET = np.array([0.0, 0.0, 0.2])
FOV_Y = math.radians(40.0)
START_Z, DROP = 0.2, 0.24  # m: the ball's centre falls from 0.2 m to -0.04 m
FRAMES = 10


def falling_ball(tmp_path):
    import torch

    from physgm.cameras import look_at
    from physgm.view.sequence import GaussianSequence, StoredFrames, matrix_to_triu

    rng = np.random.default_rng(0)
    n = 300
    x = rng.normal(size=(n, 3))
    x = x / np.linalg.norm(x, axis=1, keepdims=True) * rng.uniform(0, 1, (n, 1)) ** (1 / 3) * 0.05
    t = np.arange(FRAMES) / (FRAMES - 1)
    means = (
        x[None] + np.array([0.0, 0.0, START_Z])[None, None] - DROP * t[:, None, None] * np.array([0, 0, 1.0])
    )
    covs = np.broadcast_to(matrix_to_triu(np.eye(3) * 0.012**2), (FRAMES, n, 6))
    c2w = look_at(torch.tensor(EYE)[None], torch.tensor(TARGET)[None])[0].numpy()
    seq = GaussianSequence(colors=np.tile([0.9, 0.05, 0.05], (n, 1)), opacities=np.full(n, 0.95),
                           motion=StoredFrames(means, np.ascontiguousarray(covs)), n_frames=FRAMES, fps=25.0,
                           camera_c2w=c2w, camera_fov_y=FOV_Y, ground=-0.1)  # fmt: skip
    path = tmp_path / "run" / "gaussians_t.npz"
    path.parent.mkdir()
    seq.save(path)
    return path.parent


def projected_row(z: float) -> float:
    """Image row (px from the top) of a point at height z on the camera's axis plane."""
    focal = 0.5 * HEIGHT / math.tan(0.5 * FOV_Y)
    return 0.5 * HEIGHT - focal * (z - EYE[2]) / (EYE[0] - 0.0)


def red_pixels(img: np.ndarray) -> np.ndarray:  # [K, 2] (row, col)
    r, g, b = (img[..., i].astype(int) for i in range(3))
    return np.argwhere((r - g > 60) & (np.abs(g - b) < 30))


def wait_for(browser, predicate, timeout: float = 45.0):
    """The first screenshot that satisfies ``predicate`` (or the last one after ``timeout`` s)."""
    from physgm.view.browser import dismiss_notifications

    deadline = time.monotonic() + timeout
    shot = None
    while time.monotonic() < deadline:
        dismiss_notifications(browser)  # viser's "software WebGL" notice would cover the corner
        shot = browser.screenshot()
        if predicate(shot):
            return shot
        time.sleep(0.3)
    return shot


def test_viewer_shows_the_object_and_it_moves_with_the_slider(tmp_path):
    from physgm.view.browser import HeadlessBrowser
    from physgm.view.sequence import GaussianSequence
    from physgm.view.server import SequenceViewer, find_sequence

    seq = GaussianSequence.load(find_sequence(falling_ball(tmp_path)))
    viewer = SequenceViewer(seq, port=0, frame=0, playing=False)
    try:
        with HeadlessBrowser(WIDTH, HEIGHT) as browser:
            browser.open(viewer.url)
            # Wait until the ball is fully faded in: its pixel count stops growing.
            counts = []

            def settled(img):
                counts.append(len(red_pixels(img)))
                return len(counts) > 2 and counts[-1] > 300 and counts[-1] == counts[-2] == counts[-3]

            first = wait_for(browser, settled)
            start = red_pixels(first)
            assert len(start) > 300, f"the ball is not visible: {len(start)} red pixels; counts {counts}"
            row0, col0 = start.mean(0)
            assert abs(row0 - projected_row(START_Z)) < 12, (row0, projected_row(START_Z))
            assert abs(col0 - WIDTH / 2) < 12, col0
            # The slider moves it: the last frame is DROP lower, seen DROP * focal / distance px lower.
            viewer.set_frame(FRAMES - 1)
            assert viewer.time_text.value == f"{(FRAMES - 1) / 25:.3f}"
            end_row = projected_row(START_Z - DROP)
            last = wait_for(browser, lambda img: abs(red_pixels(img)[:, 0].mean() - end_row) < 12)
            end = red_pixels(last)
            assert len(end) > 300, f"the ball vanished after moving the slider: {len(end)} red pixels"
            row1, col1 = end.mean(0)
            assert abs(row1 - end_row) < 12 and abs(col1 - col0) < 5, (row0, row1, end_row, col0, col1)
            assert row1 - row0 > 100  # it moved, downwards, by about 150 px
            # Back to frame 0: the ball is where it started.
            viewer.set_frame(0)
            back = wait_for(browser, lambda img: abs(red_pixels(img)[:, 0].mean() - row0) < 3)
            assert abs(red_pixels(back)[:, 0].mean() - row0) < 3
    finally:
        viewer.close()


def test_screenshot_command_saves_the_frame_asked_for(tmp_path):
    """``python -m physgm.view RUN --frame 9 --screenshot out.png``: the ball where frame 9 has it."""
    from PIL import Image

    from physgm.view.__main__ import main

    out = tmp_path / "shot.png"
    assert main([str(falling_ball(tmp_path)), "--frame", str(FRAMES - 1), "--screenshot", str(out),
                 "--size", str(WIDTH), str(HEIGHT)]) == 0  # fmt: skip
    img = np.asarray(Image.open(out).convert("RGB"))
    assert img.shape == (HEIGHT, WIDTH, 3)
    ball = red_pixels(img)
    assert len(ball) > 300, f"the ball is not in the screenshot: {len(ball)} red pixels"
    assert abs(ball[:, 0].mean() - projected_row(START_Z - DROP)) < 12
