"""Simulated Gaussians over time, the file the 4D viewer reads (``gaussians_t.npz`` in a run folder).

Only what changes is stored per frame: centres and covariances (the colours and opacities of the
first frame hold for all frames, as the simulation carries them unchanged). Covariances, not
(quat, scale) pairs, because they are what a splat renderer draws and they interpolate without
the sign and axis-order ambiguities of an eigen split. The frames after the simulation came to
rest repeat the last moving one, so they are not stored: ``frame(t)`` clamps to it.

Layout of the .npz (every array little-endian, float32 unless said):
    format        int64 scalar, FORMAT_VERSION
    colors        [N, 3] RGB in [0, 1]
    opacities     [N] in [0, 1]
    means         [S, N, 3] m, S stored frames (S <= n_frames)
    covs          [S, N, 6] m^2, upper triangle (xx, xy, xz, yy, yz, zz)
    n_frames      int64 scalar, T frames of the clip
    fps           float64 scalar, frames per second
    camera_c2w    [4, 4] the clip's camera, camera-to-world (OpenCV)
    camera_fov_y  float64 scalar, vertical field of view of that camera, rad
    ground        float64 scalar, height of the ground plane in m (NaN: the scene has none)
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FORMAT_VERSION = 1
SEQUENCE_FILE = "gaussians_t.npz"
_TRIU = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))  # rows, cols of (xx, xy, xz, yy, yz, zz)


def sequence_file(run_name: str) -> str:
    """File name of one simulated future in a run folder, next to its video (``video_<name>.mp4``)."""
    return SEQUENCE_FILE if run_name == "mean" else f"gaussians_t_{run_name}.npz"


@dataclass
class GaussianSequence:
    """T frames of N Gaussians whose centres and covariances move (frame 0 = rest).

    Attributes:
        colors: [N, 3] RGB in [0, 1].
        opacities: [N] in [0, 1].
        means: [S, N, 3] centres per stored frame, m.
        covs: [S, N, 6] covariance upper triangles (xx, xy, xz, yy, yz, zz) per stored frame, m^2.
        n_frames: T frames of the clip (S <= T; frames from S on repeat frame S - 1).
        fps: frames per second of the clip.
        camera_c2w: [4, 4] camera-to-world of the clip's camera (OpenCV: x right, y down, z forward).
        camera_fov_y: vertical field of view of that camera, rad.
        ground: height of the ground plane, m, or None when the scene has no ground.
    """

    colors: np.ndarray  # [N, 3]
    opacities: np.ndarray  # [N]
    means: np.ndarray  # [S, N, 3]
    covs: np.ndarray  # [S, N, 6]
    n_frames: int
    fps: float
    camera_c2w: np.ndarray  # [4, 4]
    camera_fov_y: float
    ground: float | None = None

    def __post_init__(self) -> None:
        n = self.colors.shape[0] if self.colors.ndim == 2 else -1
        s = self.means.shape[0] if self.means.ndim == 3 else -1
        expected = {
            "colors": (n, 3),
            "opacities": (n,),
            "means": (s, n, 3),
            "covs": (s, n, 6),
            "camera_c2w": (4, 4),
        }
        for name, shape in expected.items():
            got = tuple(getattr(self, name).shape)
            if got != shape or min(shape) < 1:
                raise ValueError(
                    f"GaussianSequence.{name} must have shape {shape} (S frames, N Gaussians), got {got}"
                )
        if not 1 <= s <= self.n_frames:
            raise ValueError(
                f"GaussianSequence stores {s} frames of a {self.n_frames}-frame clip; need 1 <= stored "
                f"<= total"
            )
        if not (self.fps > 0 and math.isfinite(self.fps)) or not 0 < self.camera_fov_y < math.pi:
            raise ValueError(
                f"GaussianSequence needs fps > 0 and 0 < camera_fov_y < pi, got {self.fps}, "
                f"{self.camera_fov_y}"
            )
        for name in ("colors", "opacities", "means", "covs", "camera_c2w"):
            if not np.isfinite(getattr(self, name)).all():
                raise ValueError(f"GaussianSequence.{name} has non-finite values")

    def __len__(self) -> int:
        return self.n_frames

    @property
    def stored_frames(self) -> int:
        return self.means.shape[0]

    def frame(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """(centres [N, 3] m, covariances [N, 3, 3] m^2) at frame t in [0, T)."""
        if not 0 <= t < self.n_frames:
            raise IndexError(f"frame {t} is outside the clip's {self.n_frames} frames")
        s = min(t, self.stored_frames - 1)
        return self.means[s], triu_to_matrix(self.covs[s])

    def save(self, path: str | os.PathLike) -> Path:
        """Write the .npz atomically: a temporary sibling renamed into place, so an existing file is whole."""
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
        arrays = {
            "format": np.int64(FORMAT_VERSION),
            "colors": self.colors.astype(np.float32),
            "opacities": self.opacities.astype(np.float32),
            "means": self.means.astype(np.float32),
            "covs": self.covs.astype(np.float32),
            "n_frames": np.int64(self.n_frames),
            "fps": np.float64(self.fps),
            "camera_c2w": self.camera_c2w.astype(np.float64),
            "camera_fov_y": np.float64(self.camera_fov_y),
            "ground": np.float64(np.nan if self.ground is None else self.ground),
        }
        try:
            # Uncompressed: float coordinates barely compress (8 %) and zlib took 0.5 s for 50 frames.
            with open(tmp, "wb") as f:  # a file object: np.savez would append ".npz" to the temporary name
                np.savez(f, **arrays)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        return path

    @staticmethod
    def load(path: str | os.PathLike) -> GaussianSequence:
        """Read a file written by ``save``; a missing key or a newer format is an error that says so."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except (OSError, ValueError) as err:
            raise ValueError(f"{path} is not a readable Gaussian sequence (.npz): {err}") from None
        version = int(arrays.get("format", -1))
        if version != FORMAT_VERSION:
            raise ValueError(
                f"{path} has Gaussian sequence format {version}; this physgm reads format {FORMAT_VERSION}. "
                "Re-run simulate.py with this version to rewrite it"
            )
        missing = sorted(
            {
                "colors",
                "opacities",
                "means",
                "covs",
                "n_frames",
                "fps",
                "camera_c2w",
                "camera_fov_y",
                "ground",
            }
            - set(arrays)
        )
        if missing:
            raise ValueError(
                f"{path} lacks the array(s) {missing}; it was not written by physgm's simulate.py"
            )
        ground = float(arrays["ground"])
        return GaussianSequence(
            colors=arrays["colors"],
            opacities=arrays["opacities"],
            means=arrays["means"],
            covs=arrays["covs"],  # noqa: E501
            n_frames=int(arrays["n_frames"]),
            fps=float(arrays["fps"]),
            camera_c2w=arrays["camera_c2w"],
            camera_fov_y=float(arrays["camera_fov_y"]),
            ground=None if math.isnan(ground) else ground,
        )


def matrix_to_triu(covs: np.ndarray) -> np.ndarray:
    """[..., 3, 3] symmetric -> [..., 6] upper triangle (xx, xy, xz, yy, yz, zz)."""
    return covs[..., _TRIU[0], _TRIU[1]]


def triu_to_matrix(triu: np.ndarray) -> np.ndarray:
    """[..., 6] upper triangle -> [..., 3, 3] symmetric."""
    out = np.empty((*triu.shape[:-1], 3, 3), triu.dtype)
    out[..., _TRIU[0], _TRIU[1]] = triu
    out[..., _TRIU[1], _TRIU[0]] = triu
    return out


def sequence_from_trajectory(trajectory, camera, fps: float, ground: float | None = None) -> GaussianSequence:
    """The moving Gaussians of a ``physgm.sim.gaussian_trajectory.GaussianTrajectory`` as seen in its clip.

    Args:
        trajectory: the simulation (T frames, rest frame and deformed Gaussians per frame).
        camera: ``physgm.cameras.Cameras`` of the clip (the first camera is stored).
        fps: frames per second of the clip.
        ground: ground height, m (None: no ground).
    """
    import torch

    n_frames = len(trajectory)
    rest = trajectory.rest_frame
    stored = n_frames if rest is None else max(1, min(rest, n_frames))
    rest_g = trajectory.gaussians
    means, covs = [], []
    with torch.no_grad():
        for t in range(stored):
            g = trajectory.gaussians_at(t)
            means.append(g.means.detach().float().cpu().numpy())
            covs.append(matrix_to_triu(g.covariances().detach().float().cpu().numpy()))
    fy, height = float(camera.Ks[0, 1, 1]), float(camera.height)
    return GaussianSequence(
        colors=rest_g.colors.detach().float().cpu().numpy(),
        opacities=rest_g.opacities.detach().float().cpu().numpy(),
        means=np.stack(means),
        covs=np.stack(covs),
        n_frames=n_frames,
        fps=float(fps),
        camera_c2w=camera.c2w[0].detach().double().cpu().numpy(),
        camera_fov_y=2.0 * math.atan(0.5 * height / fy),
        ground=ground,
    )
