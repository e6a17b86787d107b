"""How a ``GaussianSequence``'s Gaussians move: the three forms a sequence file stores.

A simulated clip moves every Gaussian with a few thousand particles (or one rigid pose), so a
file stores that motion and each frame is computed when it is read (docs/viewer.md).
``StoredFrames`` keeps the explicit form: what files of format 1 hold, and what a clip with more
particles than Gaussians stores, since it is then the smaller.

Covariances travel as upper triangles (xx, xy, xz, yy, yz, zz): what a splat renderer draws,
without the sign and axis-order ambiguities of an eigen split.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

import numpy as np

if TYPE_CHECKING:  # torch and the simulator's coupling load only when a followed frame is computed
    import torch

    from physgm.sim.sampling import Followers

_TRIU = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))  # rows, cols of (xx, xy, xz, yy, yz, zz)


def matrix_to_triu(covs: np.ndarray) -> np.ndarray:
    """[..., 3, 3] symmetric -> [..., 6] upper triangle (xx, xy, xz, yy, yz, zz)."""
    return covs[..., _TRIU[0], _TRIU[1]]


def triu_to_matrix(triu: np.ndarray) -> np.ndarray:
    """[..., 6] upper triangle -> [..., 3, 3] symmetric."""
    out = np.empty((*triu.shape[:-1], 3, 3), triu.dtype)
    out[..., _TRIU[0], _TRIU[1]] = triu
    out[..., _TRIU[1], _TRIU[0]] = triu
    return out


def _check_shapes(owner: str, arrays: dict[str, tuple[np.ndarray, tuple[int, ...]]]) -> None:
    for name, (value, shape) in arrays.items():
        if tuple(value.shape) != shape or min(shape, default=1) < 1:
            raise ValueError(f"{owner}.{name} must have shape {shape}, got {tuple(value.shape)}")
        if value.dtype.kind == "f" and not np.isfinite(value).all():
            raise ValueError(f"{owner}.{name} has non-finite values")


def _bounds_by_frames(motion) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """``bounds`` exactly: each stored frame of ``motion`` computed once."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    total, var = np.zeros(3), 0.0
    diag = np.arange(3)
    for s in range(motion.stored_frames):
        means, covs = motion.frame(s)
        lo, hi = np.minimum(lo, means.min(0)), np.maximum(hi, means.max(0))
        total += means.sum(0, dtype=np.float64)
        var = max(var, float(covs[:, diag, diag].max()))
    return lo, hi, total / (motion.stored_frames * motion.n_gaussians), var


@dataclass
class StoredFrames:
    """Every stored frame's centres and covariances.

    Attributes:
        means: [S, N, 3] centres per stored frame, m.
        covs: [S, N, 6] covariance upper triangles per stored frame, m^2.
    """

    kind: ClassVar[str] = "frames"
    means: np.ndarray  # [S, N, 3]
    covs: np.ndarray  # [S, N, 6]

    def __post_init__(self) -> None:
        s, n = self.means.shape[:2] if self.means.ndim == 3 else (-1, -1)
        _check_shapes("StoredFrames", {"means": (self.means, (s, n, 3)), "covs": (self.covs, (s, n, 6))})

    @property
    def n_gaussians(self) -> int:
        return self.means.shape[1]

    @property
    def stored_frames(self) -> int:
        return self.means.shape[0]

    def frame(self, s: int) -> tuple[np.ndarray, np.ndarray]:  # [N, 3] m, [N, 3, 3] m^2
        return self.means[s], triu_to_matrix(self.covs[s])

    def bounds(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """lo [3], hi [3] and mean [3] of the centres over the stored frames (m), and the largest
        variance along an axis (m^2): ``GaussianSequence.extent``."""
        return _bounds_by_frames(self)


@dataclass
class FollowedParticles:
    """Gaussians that follow simulated particles (``physgm.sim.sampling.Followers``).

    Gaussian i's centre is sum_k w_ik (x_j + F_j o_ik) and its covariance F_i Sigma_i F_i^T with
    F_i = sum_k w_ik F_j (j = index[i, k]): what ``physgm.sim.coupling.follow_and_deform`` draws.

    Attributes:
        rest_covs: [N, 6] rest covariance upper triangles, m^2.
        index: [N, K] particle each Gaussian follows.
        weight: [N, K] their weights (each row sums to 1).
        offset: [N, K, 3] rest offsets from those particles, m.
        x: [S, P, 3] particle positions per stored frame, m.
        F: [S, P, 3, 3] particle deformation gradients per stored frame.
    """

    kind: ClassVar[str] = "particles"
    rest_covs: np.ndarray  # [N, 6]
    index: np.ndarray  # [N, K]
    weight: np.ndarray  # [N, K]
    offset: np.ndarray  # [N, K, 3]
    x: np.ndarray  # [S, P, 3]
    F: np.ndarray  # [S, P, 3, 3]
    _followers: Followers | None = field(default=None, init=False, repr=False, compare=False)
    _covs0: torch.Tensor | None = field(default=None, init=False, repr=False, compare=False)  # [N, 3, 3]

    def __post_init__(self) -> None:
        n, k = self.index.shape if self.index.ndim == 2 else (-1, -1)
        s, p = self.x.shape[:2] if self.x.ndim == 3 else (-1, -1)
        _check_shapes(
            "FollowedParticles",
            {
                "rest_covs": (self.rest_covs, (n, 6)),
                "weight": (self.weight, (n, k)),
                "offset": (self.offset, (n, k, 3)),
                "x": (self.x, (s, p, 3)),
                "F": (self.F, (s, p, 3, 3)),
            },
        )
        if self.index.min() < 0 or self.index.max() >= p:
            raise ValueError(f"FollowedParticles.index must name particles 0 to {p - 1}")

    @property
    def n_gaussians(self) -> int:
        return self.index.shape[0]

    @property
    def stored_frames(self) -> int:
        return self.x.shape[0]

    def frame(self, s: int) -> tuple[np.ndarray, np.ndarray]:  # [N, 3] m, [N, 3, 3] m^2
        import torch

        from physgm.sim.coupling import follow_covariances
        from physgm.sim.sampling import Followers

        if self._followers is None:  # torch views of the arrays, made once
            self._followers = Followers(
                torch.from_numpy(self.index.astype(np.int32)),  # what the kernel reads: no copy a frame
                torch.from_numpy(self.weight.astype(np.float32)),
                torch.from_numpy(self.offset.astype(np.float32)),
            )
            self._covs0 = torch.from_numpy(triu_to_matrix(self.rest_covs.astype(np.float32)))
        means, covs = follow_covariances(
            self._followers, self._covs0, torch.from_numpy(self.x[s]), torch.from_numpy(self.F[s])
        )
        return means.numpy(), covs.numpy()

    def bounds(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """As ``StoredFrames.bounds``, from the particles alone (no frame computed).

        The mean centre is exact: it is linear in the particles. lo, hi and the variance are
        bounds. A centre, sum_k w_k (x_j + F_j o_k), lies within max_j |F_j| max |o| of the
        particles' box (|.| the Frobenius norm), and F_i = sum_k w_k F_j has |F_i| <= max_j |F_j|,
        so a diagonal entry of F_i Sigma_i F_i^T is at most max_j |F_j|^2 max_i trace(Sigma_i).
        """
        x, F = self.x.astype(np.float64), self.F.astype(np.float64)
        w, index, p = self.weight.astype(np.float64), self.index.ravel(), self.x.shape[1]
        # Each particle's share of the sum over Gaussians: its total weight and weighted offset.
        share = np.bincount(index, w.ravel(), p)  # [P]
        lever = (w[..., None] * self.offset).reshape(-1, 3)
        lever = np.stack([np.bincount(index, lever[:, a], p) for a in range(3)], -1)  # [P, 3]
        total = (share @ x).sum(0) + np.einsum("spab,pb->a", F, lever)
        centre = total / (self.stored_frames * self.n_gaussians)
        f_max = np.sqrt((F * F).sum((-2, -1))).max(1)  # [S]
        reach = f_max * float(np.sqrt((self.offset.astype(np.float64) ** 2).sum(-1)).max())  # [S] m
        lo = (x.min(1) - reach[:, None]).min(0)
        hi = (x.max(1) + reach[:, None]).max(0)
        trace = self.rest_covs[:, 0] + self.rest_covs[:, 3] + self.rest_covs[:, 5]
        return lo, hi, centre, float(f_max.max() ** 2 * trace.max())

    @property
    def stored_bytes(self) -> int:
        """Bytes ``motion_arrays`` writes, without making them."""
        fields = _FIELDS[self.kind][1].values()
        return sum(getattr(self, name).size * np.dtype(dtype).itemsize for name, dtype in fields)


@dataclass
class RigidPoses:
    """Gaussians of one rigid body: frame s puts rest point X at rotations[s] (X - rest_com) + coms[s].

    Attributes:
        rest_means: [N, 3] rest centres, m.
        rest_covs: [N, 6] rest covariance upper triangles, m^2.
        rotations: [S, 3, 3] per stored frame.
        coms: [S, 3] centre of mass per stored frame, m.
        rest_com: [3] rest centre of mass, m.
    """

    kind: ClassVar[str] = "rigid"
    rest_means: np.ndarray  # [N, 3]
    rest_covs: np.ndarray  # [N, 6]
    rotations: np.ndarray  # [S, 3, 3]
    coms: np.ndarray  # [S, 3]
    rest_com: np.ndarray  # [3]

    def __post_init__(self) -> None:
        n = self.rest_means.shape[0] if self.rest_means.ndim == 2 else -1
        s = self.rotations.shape[0] if self.rotations.ndim == 3 else -1
        _check_shapes(
            "RigidPoses",
            {
                "rest_means": (self.rest_means, (n, 3)),
                "rest_covs": (self.rest_covs, (n, 6)),
                "rotations": (self.rotations, (s, 3, 3)),
                "coms": (self.coms, (s, 3)),
                "rest_com": (self.rest_com, (3,)),
            },
        )

    @property
    def n_gaussians(self) -> int:
        return self.rest_means.shape[0]

    @property
    def stored_frames(self) -> int:
        return self.rotations.shape[0]

    def frame(self, s: int) -> tuple[np.ndarray, np.ndarray]:  # [N, 3] m, [N, 3, 3] m^2
        rot = self.rotations[s].astype(np.float64)
        means = (self.rest_means - self.rest_com) @ rot.T + self.coms[s]
        covs = rot @ triu_to_matrix(self.rest_covs.astype(np.float64)) @ rot.T
        return means.astype(np.float32), covs.astype(np.float32)

    def bounds(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """As ``StoredFrames.bounds``: each stored frame computed once."""
        return _bounds_by_frames(self)


Motion = StoredFrames | FollowedParticles | RigidPoses

# The arrays of each kind in a file: the field each fills and its type there.
_FIELDS: dict[str, tuple[type, dict[str, tuple[str, type]]]] = {
    "frames": (StoredFrames, {"means": ("means", np.float32), "covs": ("covs", np.float32)}),
    "particles": (
        FollowedParticles,
        {
            "rest_covs": ("rest_covs", np.float32),
            "follow_index": ("index", np.int32),
            "follow_weight": ("weight", np.float32),
            "follow_offset": ("offset", np.float32),
            "particle_x": ("x", np.float32),
            "particle_F": ("F", np.float32),
        },
    ),
    "rigid": (
        RigidPoses,
        {
            "rest_means": ("rest_means", np.float32),
            "rest_covs": ("rest_covs", np.float32),
            "rigid_rotations": ("rotations", np.float64),
            "rigid_coms": ("coms", np.float64),
            "rigid_rest_com": ("rest_com", np.float64),
        },
    ),
}


def motion_arrays(motion: Motion) -> dict[str, np.ndarray]:
    """The arrays a file stores for ``motion``, by name, in their file types."""
    fields = _FIELDS[motion.kind][1]
    return {key: getattr(motion, name).astype(dtype) for key, (name, dtype) in fields.items()}


def motion_keys(kind: str) -> set[str]:
    """The arrays a file of motion ``kind`` holds; an unknown kind is an error naming the known ones."""
    if kind not in _FIELDS:
        raise ValueError(f"unknown motion {kind!r}; a sequence file holds one of {sorted(_FIELDS)}")
    return set(_FIELDS[kind][1])


def motion_from_arrays(kind: str, arrays: dict[str, np.ndarray]) -> Motion:
    """The motion of ``kind`` from a file's arrays (``motion_keys(kind)`` must all be there)."""
    cls, fields = _FIELDS[kind]
    return cls(**{name: arrays[key] for key, (name, _) in fields.items()})
