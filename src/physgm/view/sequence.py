"""Simulated Gaussians over time, the file the 4D viewer reads (``gaussians_t.npz`` in a run folder).

The colours and opacities of the rest state hold for every frame (the simulation carries them
unchanged); what moves is stored as the motion that moved it (``physgm.view.motion``): the
particles each Gaussian follows, or a rigid body's poses, from which ``frame(t)`` computes the
centres and covariances. The frames after the simulation came to rest repeat the last moving one,
so they are not stored: ``frame(t)`` clamps to it.

Layout of the .npz (little-endian; float32 unless said):
    format        int64 scalar, FORMAT_VERSION (files of format 1 hold ``frames`` and still load)
    motion        str scalar: "particles", "rigid" or "frames"
    colors        [N, 3] RGB in [0, 1]
    opacities     [N] in [0, 1]
    n_frames      int64 scalar, T frames of the clip
    fps           float64 scalar, frames per second
    camera_c2w    [4, 4] float64, the clip's camera, camera-to-world (OpenCV)
    camera_fov_y  float64 scalar, vertical field of view of that camera, rad
    ground        float64 scalar, height of the ground plane in m (NaN: the scene has none)
  "particles" (S stored frames, P particles, K followed particles per Gaussian):
    rest_covs [N, 6] m^2 (upper triangle xx, xy, xz, yy, yz, zz); follow_index [N, K] int32;
    follow_weight [N, K]; follow_offset [N, K, 3] m; particle_x [S, P, 3] m; particle_F [S, P, 3, 3]
  "rigid":
    rest_means [N, 3] m; rest_covs [N, 6] m^2; rigid_rotations [S, 3, 3], rigid_coms [S, 3] m and
    rigid_rest_com [3] m, float64
  "frames":
    means [S, N, 3] m; covs [S, N, 6] m^2
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from physgm.view.motion import (
    FollowedParticles,
    Motion,
    RigidPoses,
    StoredFrames,
    matrix_to_triu,
    motion_arrays,
    motion_from_arrays,
    motion_keys,
    triu_to_matrix,
)

__all__ = [
    "FORMAT_VERSION",
    "SEQUENCE_FILE",
    "FollowedParticles",
    "GaussianSequence",
    "RigidPoses",
    "SequenceExtent",
    "StoredFrames",
    "matrix_to_triu",
    "sequence_file",
    "sequence_from_trajectory",
    "triu_to_matrix",
]

FORMAT_VERSION = 2
SEQUENCE_FILE = "gaussians_t.npz"
_COMMON = ("colors", "opacities", "n_frames", "fps", "camera_c2w", "camera_fov_y", "ground")


def sequence_file(run_name: str) -> str:
    """File name of one simulated future in a run folder, next to its video (``video_<name>.mp4``)."""
    return SEQUENCE_FILE if run_name == "mean" else f"gaussians_t_{run_name}.npz"


@dataclass
class SequenceExtent:
    """Where a clip's Gaussians go over all its frames.

    Attributes:
        lo, hi: [3] lowest and highest centre coordinates over the frames, or bounds on them, m.
        centre: [3] mean centre over the frames and Gaussians, m.
        max_variance: the largest variance along an axis over the frames, or a bound on it, m^2.
    """

    lo: np.ndarray
    hi: np.ndarray
    centre: np.ndarray
    max_variance: float


@dataclass
class GaussianSequence:
    """T frames of N Gaussians whose centres and covariances move (frame 0 = rest).

    Attributes:
        colors: [N, 3] RGB in [0, 1].
        opacities: [N] in [0, 1].
        motion: how the centres and covariances move over the S stored frames
            (``physgm.view.motion``: ``FollowedParticles``, ``RigidPoses`` or ``StoredFrames``).
        n_frames: T frames of the clip (S <= T; frames from S on repeat frame S - 1).
        fps: frames per second of the clip.
        camera_c2w: [4, 4] camera-to-world of the clip's camera (OpenCV: x right, y down, z forward).
        camera_fov_y: vertical field of view of that camera, rad.
        ground: height of the ground plane, m, or None when the scene has no ground.
    """

    colors: np.ndarray  # [N, 3]
    opacities: np.ndarray  # [N]
    motion: Motion
    n_frames: int
    fps: float
    camera_c2w: np.ndarray  # [4, 4]
    camera_fov_y: float
    ground: float | None = None

    def __post_init__(self) -> None:
        n = self.motion.n_gaussians
        expected = {"colors": (n, 3), "opacities": (n,), "camera_c2w": (4, 4)}
        for name, shape in expected.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(
                    f"GaussianSequence.{name} must have shape {shape} ({n} Gaussians move), got {got}"
                )
            if not np.isfinite(getattr(self, name)).all():
                raise ValueError(f"GaussianSequence.{name} has non-finite values")
        if not 1 <= self.stored_frames <= self.n_frames:
            raise ValueError(
                f"GaussianSequence stores {self.stored_frames} frames of a {self.n_frames}-frame clip; "
                "need 1 <= stored <= total"
            )
        if not (self.fps > 0 and math.isfinite(self.fps)) or not 0 < self.camera_fov_y < math.pi:
            raise ValueError(
                f"GaussianSequence needs fps > 0 and 0 < camera_fov_y < pi, got {self.fps}, "
                f"{self.camera_fov_y}"
            )

    def __len__(self) -> int:
        return self.n_frames

    @property
    def stored_frames(self) -> int:
        return self.motion.stored_frames

    def frame(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """(centres [N, 3] m, covariances [N, 3, 3] m^2) at frame t in [0, T)."""
        if not 0 <= t < self.n_frames:
            raise IndexError(f"frame {t} is outside the clip's {self.n_frames} frames")
        return self.motion.frame(min(t, self.stored_frames - 1))

    def extent(self) -> SequenceExtent:
        """Where the Gaussians go over the stored frames (``bounds`` of the motion: each frame
        computed once, or for Gaussians that follow particles, bounds from the particles alone)."""
        return SequenceExtent(*self.motion.bounds())

    def save(self, path: str | os.PathLike) -> Path:
        """Write the .npz atomically: a temporary sibling renamed into place, so an existing file is whole."""
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
        arrays = {
            "format": np.int64(FORMAT_VERSION),
            "motion": np.str_(self.motion.kind),
            "colors": self.colors.astype(np.float32),
            "opacities": self.opacities.astype(np.float32),
            **motion_arrays(self.motion),
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
        """Read a file written by ``save`` (or by a physgm of format 1); a missing array or a newer
        format is an error that says so."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except (OSError, ValueError) as err:
            raise ValueError(f"{path} is not a readable Gaussian sequence (.npz): {err}") from None
        version = int(arrays.get("format", -1))
        if version not in (1, FORMAT_VERSION):
            raise ValueError(
                f"{path} has Gaussian sequence format {version}; this physgm reads formats 1 and "
                f"{FORMAT_VERSION}. Re-run simulate.py with this version to rewrite it"
            )
        kind = "frames" if version == 1 else str(arrays.get("motion", ""))
        try:
            needed = motion_keys(kind)
        except ValueError as err:
            raise ValueError(f"{path}: {err}") from None
        missing = sorted((set(_COMMON) | needed) - set(arrays))
        if missing:
            raise ValueError(
                f"{path} lacks the array(s) {missing}; it was not written by physgm's simulate.py"
            )
        ground = float(arrays["ground"])
        return GaussianSequence(
            colors=arrays["colors"],
            opacities=arrays["opacities"],
            motion=motion_from_arrays(kind, arrays),
            n_frames=int(arrays["n_frames"]),
            fps=float(arrays["fps"]),
            camera_c2w=arrays["camera_c2w"],
            camera_fov_y=float(arrays["camera_fov_y"]),
            ground=None if math.isnan(ground) else ground,
        )


def sequence_from_trajectory(trajectory, camera, fps: float, ground: float | None = None) -> GaussianSequence:
    """The moving Gaussians of a ``physgm.sim.gaussian_trajectory.GaussianTrajectory`` as seen in its clip.

    Args:
        trajectory: the simulation (T frames, its rest frame, and the particles or rigid poses that move
            its rest Gaussians); its motion is stored, not each frame's Gaussians, unless its
            particles would take more room than the Gaussians' centres and covariances.
        camera: ``physgm.cameras.Cameras`` of the clip (the first camera is stored).
        fps: frames per second of the clip.
        ground: ground height, m (None: no ground).
    """
    n_frames = len(trajectory)
    rest = trajectory.rest_frame
    stored = n_frames if rest is None else max(1, min(rest, n_frames))
    g = trajectory.gaussians
    rest_covs = matrix_to_triu(g.covariances().detach().float().cpu().numpy())
    if trajectory.rigid is not None:
        rigid = trajectory.rigid
        motion = RigidPoses(
            rest_means=g.means.detach().float().cpu().numpy(),
            rest_covs=rest_covs,
            rotations=rigid.rotations[:stored],
            coms=rigid.coms[:stored],
            rest_com=np.asarray(rigid.rest_com, np.float64),
        )
    else:
        f = trajectory.followers
        motion = FollowedParticles(
            rest_covs=rest_covs,
            index=f.index.cpu().numpy().astype(np.int32),
            weight=f.weight.detach().float().cpu().numpy(),
            offset=f.offset.detach().float().cpu().numpy(),
            x=trajectory.x[:stored],
            F=trajectory.F[:stored],
        )
        if motion.stored_bytes > 36 * stored * motion.n_gaussians:  # the particles would take more room
            frames = [motion.frame(s) for s in range(stored)]
            motion = StoredFrames(
                means=np.stack([m for m, _ in frames]), covs=np.stack([matrix_to_triu(c) for _, c in frames])
            )
    fy, height = float(camera.Ks[0, 1, 1]), float(camera.height)
    return GaussianSequence(
        colors=g.colors.detach().float().cpu().numpy(),
        opacities=g.opacities.detach().float().cpu().numpy(),
        motion=motion,
        n_frames=n_frames,
        fps=float(fps),
        camera_c2w=camera.c2w[0].detach().double().cpu().numpy(),
        camera_fov_y=2.0 * math.atan(0.5 * height / fy),
        ground=ground,
    )
