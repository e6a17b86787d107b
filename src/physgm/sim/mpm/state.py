"""Typed containers of the simulator: input particles, returned state, per-frame statistics."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Particles:
    """Input particle set (SI units). Validated on construction.

    Args:
        x: [P, 3] positions, m.
        volume: [P] rest volumes, m^3.
        material: [P] index into the material list handed to the solver.
        v: [P, 3] initial velocities, m/s (zeros if None).
        F: [P, 3, 3] initial deformation gradients (identity if None).
        C: [P, 3, 3] initial APIC affine velocities, 1/s (zeros if None).
        plastic: [P] initial plastic history (zeros if None).
    """

    x: np.ndarray  # [P, 3]
    volume: np.ndarray  # [P]
    material: np.ndarray  # [P]
    v: np.ndarray | None = None  # [P, 3]
    F: np.ndarray | None = None  # [P, 3, 3]
    C: np.ndarray | None = None  # [P, 3, 3]
    plastic: np.ndarray | None = None  # [P]

    def __post_init__(self) -> None:
        self.x = np.ascontiguousarray(self.x, dtype=np.float32)
        if self.x.ndim != 2 or self.x.shape[1] != 3:
            raise ValueError(f"particle positions must have shape [P, 3], got {self.x.shape}")
        n = self.x.shape[0]
        if n == 0:
            raise ValueError("no particles: the particle set is empty (P = 0); sample the object first")
        bad = ~np.isfinite(self.x).all(axis=1)
        if bad.any():
            raise ValueError(
                f"{int(bad.sum())} particle positions are not finite (first bad index {int(np.argmax(bad))}: "
                f"{self.x[np.argmax(bad)].tolist()}); remove NaN/inf points before simulating"
            )
        self.volume = np.broadcast_to(np.asarray(self.volume, dtype=np.float32), (n,)).copy()
        if not (np.isfinite(self.volume).all() and (self.volume > 0).all()):
            raise ValueError(
                f"particle volumes must be finite and > 0 m^3, min is {float(np.min(self.volume))!r}"
            )
        self.material = np.broadcast_to(np.asarray(self.material, dtype=np.int32), (n,)).copy()
        if (self.material < 0).any():
            raise ValueError(f"material indices must be >= 0, got min {int(self.material.min())}")
        if self.v is not None:
            self.v = np.broadcast_to(np.asarray(self.v, dtype=np.float32), (n, 3)).copy()
            if not np.isfinite(self.v).all():
                raise ValueError("initial particle velocities contain NaN/inf")
        if self.F is not None:
            self.F = np.broadcast_to(np.asarray(self.F, dtype=np.float32), (n, 3, 3)).copy()
            if not np.isfinite(self.F).all():
                raise ValueError("initial deformation gradients contain NaN/inf")
        if self.C is not None:
            self.C = np.broadcast_to(np.asarray(self.C, dtype=np.float32), (n, 3, 3)).copy()
            if not np.isfinite(self.C).all():
                raise ValueError("initial affine velocities C contain NaN/inf")
        if self.plastic is not None:
            self.plastic = np.broadcast_to(np.asarray(self.plastic, dtype=np.float32), (n,)).copy()
            if not np.isfinite(self.plastic).all():
                raise ValueError("initial plastic history contains NaN/inf")

    def __len__(self) -> int:
        return self.x.shape[0]

    @classmethod
    def lattice(
        cls,
        lo: tuple[float, float, float],
        hi: tuple[float, float, float],
        spacing: float,
        material: int = 0,
        inside=None,
    ) -> Particles:
        """Particles on a regular lattice of ``spacing`` (m) filling the box [lo, hi].

        ``inside``: optional predicate on [P, 3] positions selecting a subset (e.g. a sphere).
        Each particle gets volume spacing^3.
        """
        axes = [np.arange(a + 0.5 * spacing, b, spacing) for a, b in zip(lo, hi, strict=True)]
        x = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        if inside is not None:
            x = x[inside(x)]
        return cls(x=x, volume=spacing**3, material=material)

    @classmethod
    def cat(cls, parts: list[Particles]) -> Particles:
        """Concatenate particle sets (material indices are kept as given)."""
        n = [len(p) for p in parts]
        v = [p.v if p.v is not None else np.zeros((k, 3), np.float32) for p, k in zip(parts, n, strict=True)]
        F = [
            p.F if p.F is not None else np.tile(np.eye(3, dtype=np.float32), (k, 1, 1))
            for p, k in zip(parts, n, strict=True)
        ]
        C = [
            p.C if p.C is not None else np.zeros((k, 3, 3), np.float32) for p, k in zip(parts, n, strict=True)
        ]
        plastic = [
            p.plastic if p.plastic is not None else np.zeros(k, np.float32)
            for p, k in zip(parts, n, strict=True)
        ]
        return cls(
            x=np.concatenate([p.x for p in parts]),
            volume=np.concatenate([p.volume for p in parts]),
            material=np.concatenate([p.material for p in parts]),
            v=np.concatenate(v),
            F=np.concatenate(F),
            C=np.concatenate(C),
            plastic=np.concatenate(plastic),
        )


@dataclass
class ParticleState:
    """Solver state in the caller's particle order (numpy float32)."""

    x: np.ndarray  # [P, 3] m
    v: np.ndarray  # [P, 3] m/s
    F: np.ndarray  # [P, 3, 3] elastic deformation gradient
    C: np.ndarray  # [P, 3, 3] APIC affine velocity, 1/s
    plastic: np.ndarray  # [P] plastic history (accumulated plastic strain)
    escaped: np.ndarray  # [P] bool, stopped by the domain clamp at least once


@dataclass
class FrameStats:
    """What happened during one frame."""

    frame: int
    time: float  # s, at the end of the frame
    substeps: int
    dt_min: float  # s
    dt_max: float  # s
    cfl: float  # CFL number that succeeded
    retries: int  # divergence-guard retries this frame
    max_speed: float  # m/s
    j_min: float
    j_max: float
    escaped: int  # particles stopped by the domain clamp so far
    face_contacts: int = 0  # grid-node updates in which a grid-face wall stopped mass, so far


@dataclass
class Energy:
    """Energies of the particle system, J."""

    kinetic: float  # translational + APIC affine
    gravitational: float  # -m g . x (zero at the origin)
    elastic: float  # strain energy of the elastic deformation

    @property
    def total(self) -> float:
        return self.kinetic + self.gravitational + self.elastic


@dataclass
class Trajectory:
    """Per-frame particle states; frame 0 is the initial state."""

    x: np.ndarray  # [T, P, 3] m
    F: np.ndarray  # [T, P, 3, 3]
    stats: list[FrameStats] = field(default_factory=list)
