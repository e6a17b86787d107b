"""Time stepping: solver configuration, CFL step, divergence error."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

from physgm.resources import package_file
from physgm.setting_types import check_types
from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm.particle_ground import contact_wave_speed

CONF_DIR = package_file("conf", "sim")  # ships inside the package (physgm.resources)


class SimulationDiverged(RuntimeError):
    """The divergence guard gave up: the state stayed non-finite, J left (j_min, j_max] or fell below
    a model's floor."""


@dataclass(frozen=True)
class SolverConfig:
    """Solver settings (conf/sim/solver/default.yaml)."""

    frame_dt: float = 0.04  # s, 25 fps
    cfl: float = 0.4  # C in dt = C dx / (c_p + |v|max)
    # Affine-FLIP share of the particle (v, C) update; 0 is pure APIC. APIC damps the modes the
    # grid cannot hold on every transfer, so its energy loss grows with the number of sub-steps
    # (two elastic spheres lost 13 % of their energy in one collision at cfl 0.4, 21 % at 0.2);
    # 0.95 keeps it under 5 % and, because C is incremented with v, angular momentum stays exact.
    # Positions move with the grid velocity whatever this is (kernels.g2p_kernel; issue 24).
    flip: float = 0.95
    max_retries: int = 4  # divergence-guard retries per frame, each halving the CFL number
    # det F bounds of the divergence guard. A step is rejected (and retried smaller) when det F
    # of any particle ends at or below j_min, or when the elastic trial det F of a particle falls
    # below its constitutive model's floor (``ConstitutiveModel.j_floor``, on the elastic part so
    # plastic compaction is never rejected). det F <= 0 is an inverted or collapsed element, never
    # a state: before issue 24 the guard accepted it down to -0.5 and a jelly hit at twice its wave
    # speed kept 10 % of its particles inverted. j_max is wide on purpose: a plastic particle torn
    # off its neighbours reaches J ~ 1e3, while a diverging explicit step grows F exponentially
    # and leaves the bound (or turns NaN) within a frame.
    j_min: float = 0.0  # det F must stay above this, in [0, 1)
    j_max: float = 1.0e4  # largest det F accepted
    boundary_cells: int = 3  # separating-wall margin at the grid faces, cells
    threads: int = 0  # CPU threads for the particle kernels; 0 = auto (2 from 500 particles, solver.py)
    cfl_check_every: int = 16  # sub-steps between re-evaluations of |v|max and dt
    # Replay each run of cfl_check_every sub-steps from a launch graph captured once (a CUDA graph,
    # or Warp's C++ replay on the CPU, one graph per thread) when the solver has no grid hooks, side
    # walls or observers; same kernels, same results, less launch overhead (launches.run_graph).
    graphs: bool = True
    sort_every: int = 1  # frames between particle sorts by cell (0: only at start)
    max_substeps: int = 2_000_000  # per frame; beyond this the frame stops with an error
    max_grid_nodes: int = 64_000_000  # ~6 GB of grid arrays (96 B per node); larger grids are refused
    # "explicit" (the CFL-limited step), "implicit" (elastic models only; physgm.sim.mpm.implicit) or
    # "pressure" (elastic models, lam's volume term implicit on the grid; physgm.sim.mpm.pressure).
    integrator: str = "explicit"
    implicit_dt: float = 0.01  # s, the implicit sub-step while the body is slow (ignored by explicit)
    implicit_theta: float = 1.0  # theta method: 1 backward Euler, 0.5 implicit midpoint
    # The pressure integrator's solve stops at this rms velocity residual (m/s) or after
    # pressure_max_iterations conjugate-gradient iterations (physgm.sim.mpm.pressure).
    pressure_tolerance: float = 2.0e-4
    pressure_max_iterations: int = 100
    # Where in the sub-step the pressure integrator takes the volume term, from 0.5 (its middle) to 1
    # (its end: backward Euler); the volume waves are damped in proportion, and every value is
    # stable at any step (physgm.sim.mpm.pressure).
    pressure_theta: float = 0.6

    def __post_init__(self) -> None:
        check_types(self, "solver setting")
        rules = {  # setting -> (holds, the rule in words)
            "frame_dt": (self.frame_dt > 0, "> 0 s"),
            "cfl": (0 < self.cfl <= 1, "in (0, 1]"),
            "flip": (0 <= self.flip <= 1, "in [0, 1]"),
            "max_retries": (self.max_retries >= 0, ">= 0"),
            "j_min": (0 <= self.j_min < 1, "in [0, 1)"),
            "j_max": (self.j_max > 1, "> 1"),
            "boundary_cells": (self.boundary_cells >= 2, ">= 2"),
            "threads": (self.threads >= 0, ">= 0 (0: automatic)"),
            "cfl_check_every": (self.cfl_check_every >= 1, ">= 1"),
            "sort_every": (self.sort_every >= 0, ">= 0"),
            "max_substeps": (self.max_substeps >= 1, ">= 1"),
            "max_grid_nodes": (self.max_grid_nodes >= 512, ">= 512"),
            "implicit_dt": (self.implicit_dt > 0, "> 0 s"),
            "implicit_theta": (0.5 <= self.implicit_theta <= 1, "in [0.5, 1]"),
            "pressure_tolerance": (self.pressure_tolerance > 0, "> 0 m/s"),
            "pressure_max_iterations": (self.pressure_max_iterations >= 1, ">= 1"),
            "pressure_theta": (0.5 <= self.pressure_theta <= 1, "in [0.5, 1]"),
        }
        for name, (holds, rule) in rules.items():
            if not holds:
                raise ValueError(
                    f"solver setting {name}={getattr(self, name)!r} is out of range: it must be {rule} "
                    "(conf/sim/solver/default.yaml says what each setting does)"
                )

    @classmethod
    def from_dict(cls, values: dict) -> SolverConfig:
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown solver settings {sorted(unknown)}; known: {sorted(known)}")
        return cls(**values)

    @classmethod
    def load(cls, name: str = "default") -> SolverConfig:
        """Load conf/sim/solver/<name>.yaml."""
        import yaml

        path = CONF_DIR / "solver" / f"{name}.yaml"
        if not path.is_file():
            raise ValueError(f"no solver config {name!r} at {path}")
        return cls.from_dict(yaml.safe_load(path.read_text()) or {})


def wave_speed(materials: Sequence[MaterialParams]) -> float:
    """Largest P-wave (or sound) speed among the materials, m/s."""
    return max(m.wave_speed() for m in materials)


def step_wave_speed(materials: Sequence[MaterialParams], scene, particles, dx: float) -> float:
    """Speed c of the solver's CFL rule dt = cfl dx / (c + |v|max): the fastest material's P-wave
    speed, or more if the ground's particle contact springs need it (``particle_ground``), m/s.
    ``scene``: the solver's ``Scene``; ``particles``: its input ``Particles``."""
    spring = contact_wave_speed(
        scene.ground, materials, particles.volume, particles.material, dx, scene.gravity
    )
    return max(wave_speed(materials), spring)


def cfl_dt(
    dx: float,
    materials: Sequence[MaterialParams],
    vmax: float = 0.0,
    cfl: float = 0.4,
    speed: float | None = None,
) -> float:
    """CFL step dt = cfl dx / (c + |v|max), s: c is the materials' P-wave speed, or ``speed`` (m/s)
    when given (``implicit_step_speed``)."""
    c = wave_speed(materials) if speed is None else speed
    return cfl * dx / (c + max(vmax, 0.0))


def implicit_step_speed(cfl: float, dx: float, implicit_dt: float) -> float:
    """The implicit integrator's speed c in the CFL rule dt = cfl dx / (c + |v|max): the one that
    gives ``implicit_dt`` at rest, so a fast body takes the advective limit instead, m/s."""
    return cfl * dx / implicit_dt


def substeps_per_frame(
    dx: float,
    materials: Sequence[MaterialParams],
    vmax: float,
    cfl: float,
    frame_dt: float,
    speed: float | None = None,
) -> int:
    """Sub-steps the solver will take for one frame at speed ``vmax`` (for cost planning); ``speed``
    as in ``cfl_dt``."""
    return max(1, math.ceil(frame_dt / cfl_dt(dx, materials, vmax, cfl, speed) - 1e-9))
