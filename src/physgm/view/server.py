"""The 4D viewer: a viser server showing a ``GaussianSequence`` with a time slider and play/pause.

viser draws the splats in the browser (WebGL) and gives the free camera (drag to orbit, right-drag
to pan, scroll to zoom); this module only picks the frame to show. The camera opens where the
clip's camera was, so the first view matches video.mp4.

viser packs covariances as float16, whose normal range starts at 6e-5: a 1 mm Gaussian (variance
1e-6 m^2) would keep 2 or 3 significant bits. The splats are therefore sent in units of the
median Gaussian's size, where variances sit around 1 (unless that would overflow the largest one),
and the scene node scales them back to metres.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from physgm.view.sequence import GaussianSequence

INSTALL_HINT = "the 4D viewer needs viser: pip install 'physgm[view]' (or pip install viser)"


def import_viser():
    """viser, or an ImportError that says how to install it (viser is an optional extra)."""
    try:
        import viser
    except ImportError as err:
        raise ImportError(f"{INSTALL_HINT} ({err})") from None
    return viser


def camera_view(c2w: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(position, look-at point, up) of an OpenCV camera-to-world [4, 4] looking towards ``target`` [3].

    The look-at point is ``target`` projected on the camera's optical axis, so the view direction
    is the camera's own and orbiting turns about the object.
    """
    eye, forward, down = c2w[:3, 3], c2w[:3, 2], c2w[:3, 1]
    depth = max(float(np.dot(target - eye, forward)), 1e-3)
    return eye, eye + depth * forward, -down


class SequenceViewer:
    """Serves one ``GaussianSequence``; ``set_frame`` / ``play`` drive it from Python as the GUI does.

    Args:
        sequence: the moving Gaussians.
        host, port: where the server listens (viser moves to the next port if it is taken; 0: any free port).
        title: shown at the top of the control panel.
        frame: frame shown first.
        playing: start playing.
    """

    def __init__(
        self,
        sequence: GaussianSequence,
        host: str = "127.0.0.1",
        port: int = 8080,
        title: str = "physgm",
        frame: int = 0,
        playing: bool = True,
    ) -> None:
        viser = import_viser()
        if not 0 <= frame < len(sequence):
            raise ValueError(
                f"frame {frame} is outside the clip's {len(sequence)} frames (0 to {len(sequence) - 1})"
            )
        self.sequence = sequence
        self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        scene = self.server.scene
        scene.set_up_direction("+z")  # physgm's world is +z up
        centers0, covs0 = sequence.frame(0)
        extent = sequence.extent()  # a followed clip: from its particles; else every frame once
        variances0 = covs0[:, np.arange(3), np.arange(3)]  # [N, 3] m^2
        # m per display unit (see module doc); the largest variance stays below float16's 65504
        largest = float(np.sqrt(extent.max_variance / 1e4))
        self.unit = max(float(np.sqrt(np.median(variances0))), largest) or 1.0
        size = float(np.ptp(centers0, axis=0).max()) or 1.0  # m, the object's extent
        self._rgbs = sequence.colors.astype(np.float32)
        self._opacities = sequence.opacities.astype(np.float32)[:, None]
        self.splats = scene.add_gaussian_splats(
            "/object",
            centers=centers0 / self.unit,
            covariances=covs0 / self.unit**2,
            rgbs=self._rgbs,
            opacities=self._opacities,
            scale=self.unit,
        )
        if sequence.ground is not None:
            lo, hi = extent.lo[:2], extent.hi[:2]
            width = 4.0 * float(max(hi - lo)) + 2.0 * size
            center = 0.5 * (lo + hi)
            scene.add_grid(
                "/ground",
                width=width,
                height=width,
                cell_size=size / 4,
                section_size=size,
                position=(float(center[0]), float(center[1]), sequence.ground),
            )
        eye, look_at, up = camera_view(sequence.camera_c2w, extent.centre)  # orbit the motion
        self.server.initial_camera.position = eye
        self.server.initial_camera.look_at = look_at
        self.server.initial_camera.up = up
        self.server.initial_camera.fov = sequence.camera_fov_y

        gui = self.server.gui
        n = len(sequence)
        gui.add_markdown(
            f"**{title}**  \n{len(sequence.colors)} Gaussians, {n} frames at {sequence.fps:g} fps"
        )
        self.slider = gui.add_slider("frame", min=0, max=n - 1, step=1, initial_value=frame)
        self.time_text = gui.add_text("time (s)", initial_value=self._time_label(frame), disabled=True)
        self.play_box = gui.add_checkbox("play", initial_value=playing)
        self.speed = gui.add_slider(
            "speed",
            min=0.05,
            max=2.0,
            step=0.05,
            initial_value=1.0,
            hint="1 = real time; the simulation's time step is 1 / fps",
        )
        self.frame = -1
        self._lock = threading.Lock()
        self.slider.on_update(lambda _: self._show(int(self.slider.value)))
        self._show(frame)
        self._stop = threading.Event()
        self._player = threading.Thread(target=self._play_loop, name="physgm-view-player", daemon=True)
        self._player.start()

    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.server.get_port()}"

    def _time_label(self, t: int) -> str:
        return f"{t / self.sequence.fps:.3f}"

    def _show(self, t: int) -> None:
        with self._lock:
            if t == self.frame:
                return
            centers, covs = self.sequence.frame(t)
            self.splats.set_gaussians(centers / self.unit, covs / self.unit**2, self._rgbs, self._opacities)
            self.frame = t
            self.time_text.value = self._time_label(t)

    def set_frame(self, t: int) -> None:
        """Show frame t in every connected browser (moves the slider as a user would)."""
        if not 0 <= t < len(self.sequence):
            raise ValueError(f"frame {t} is outside the clip's {len(self.sequence)} frames")
        self.slider.value = t  # its update callback shows the frame

    def play(self, playing: bool = True) -> None:
        self.play_box.value = playing

    def _play_loop(self) -> None:
        next_tick = time.monotonic()
        while not self._stop.is_set():
            dt = 1.0 / (self.sequence.fps * max(float(self.speed.value), 1e-3))
            next_tick = max(next_tick + dt, time.monotonic())
            self._stop.wait(max(0.0, next_tick - time.monotonic()))
            if self.play_box.value and not self._stop.is_set():
                self.set_frame((self.frame + 1) % len(self.sequence))

    def close(self) -> None:
        self._stop.set()
        self._player.join(timeout=5.0)
        self.server.stop()


def find_sequence(path: str | Path, run: str = "mean") -> Path:
    """The sequence file of ``run`` in a run folder (or ``path`` itself when it is a file)."""
    from physgm.view.sequence import sequence_file

    path = Path(path)
    if path.is_file():
        return path
    if not path.is_dir():
        raise FileNotFoundError(f"{path} does not exist; give a run folder written by simulate.py")
    target = path / sequence_file(run)
    if not target.is_file():
        found = sorted(p.name for p in path.glob("gaussians_t*.npz"))
        if found:
            raise FileNotFoundError(
                f"{path} has no {target.name}; it has {found} (choose one with --run NAME)"
            )
        raise FileNotFoundError(
            f"{path} has no {target.name}: it is not a run folder of simulate.py, or one written before "
            "simulate.py saved the Gaussians over time; re-run simulate.py to write it"
        )
    return target


def save_screenshot(
    path: str | Path,
    out: str | Path,
    run: str = "mean",
    frame: int = 0,
    width: int = 960,
    height: int = 540,
    port: int = 0,
) -> Path:
    """Open the viewer on a run folder in headless Chromium at ``frame`` and save what it shows as a PNG."""
    from PIL import Image

    from physgm.view.browser import HeadlessBrowser, wait_until_still

    file = find_sequence(path, run)
    viewer = SequenceViewer(
        GaussianSequence.load(file),
        "127.0.0.1",
        port,
        f"{file.parent.name}/{file.name}",
        frame,
        playing=False,
    )
    try:
        with HeadlessBrowser(width, height) as browser:
            browser.open(viewer.url)
            deadline = time.monotonic() + browser.timeout
            while not viewer.server.get_clients():  # the page has not opened its websocket yet
                if time.monotonic() > deadline:
                    raise TimeoutError(f"the page did not connect to the viewer within {browser.timeout:g} s")
                time.sleep(0.1)
            time.sleep(2.0)  # the scene's messages follow the connection
            img = wait_until_still(browser)
    finally:
        viewer.close()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(img).save(out)
    return out


def serve(
    path: str | Path,
    run: str = "mean",
    host: str = "127.0.0.1",
    port: int = 8080,
    frame: int = 0,
    playing: bool = True,
) -> None:
    """Serve a run folder's moving Gaussians until Ctrl-C."""
    file = find_sequence(path, run)
    sequence = GaussianSequence.load(file)
    title = f"{file.parent.name}/{file.name}"
    viewer = SequenceViewer(sequence, host, port, title, frame, playing)
    print(
        f"physgm viewer: {viewer.url}  ({len(sequence.colors)} Gaussians, {len(sequence)} frames, "
        f"{len(sequence) / sequence.fps:.2f} s); Ctrl-C stops",
        flush=True,
    )
    try:
        while True:
            time.sleep(3600.0)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.close()
