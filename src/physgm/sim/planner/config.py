"""The planner's settings (conf/sim/planner/default.yaml)."""

from __future__ import annotations

from dataclasses import dataclass

from physgm.setting_types import check_types


@dataclass
class PlannerConfig:
    """Planner knobs (conf/sim/planner/default.yaml)."""

    bound_px: float = 0.5  # largest visual error allowed, pixels at the output resolution
    cells_across: int = 12  # grid cells across the object's largest extent
    # Cap on grid cells per axis: dx grows to respect it, except along z for a drop whose fall is
    # closed form, where the grid is cut above the ground and follows the body (domain.grid_region).
    max_cells: int = 96
    # MPM particles per grid cell: 8 (2 per axis) is MPM practice; at 1 per cell or fewer a soft
    # body loses its shape. Sets the particle spacing dx / ppc^(1/3); the lattice through the
    # object's bounding box then holds at most (cells_across ppc^(1/3))^3 particles (13,824).
    particles_per_cell: float = 8.0
    # Particle spacing, in cells, a stretched body may reach: MPM tears a body whose particles
    # drift about a cell apart (a 20 cm jelly cube at 2 per cell tore at 1.85x its length, at
    # 0.93 cells), so a scene that stretches splits the particles along its axis to stay below it.
    max_stretched_spacing: float = 0.67
    min_opacity: float = 0.05  # Gaussians fainter than this carry no mass
    # ... unless the object's Gaussians are all faint (translucent): then this share of their 99th
    # percentile opacity, when lower (sampling.mass_opacity); 0 keeps min_opacity alone.
    relative_opacity: float = 0.25
    fill_interior: bool = True  # fill the inside of closed Gaussian shells with particles (sampling.py)
    follower_k: int = 8  # nearest particles each Gaussian follows
    allow_rigid: bool = True  # rigid-body path for objects that would not deform visibly
    allow_stiffness_cap: bool = True  # lower E while the extra deformation stays under the bound
    min_cap_gain: float = 1.25  # cap only if it saves at least this factor of sub-steps
    cap_budget: float = 0.5  # fraction of bound_px the stiffness cap may use (rebound changes too)
    # Bulk cap (sim/bulk_cap.py): keep the shear modulus, lower nu until c_p <= ratio c_s. It may
    # use bound_px minus the stiffness cap's share (all of it when the stiffness cap saves nothing),
    # and counts the rebound of an elastic impact or the dent of a landing that yields.
    allow_bulk_cap: bool = True
    bulk_wave_ratio: float = 2.0  # smallest c_p / c_s the bulk cap may reach (2: nu = 1/3)
    force_caps: bool = False  # benchmarks: take each allowed cap whatever its predicted error
    # Run an elastic body (fixed-corotated, neo-Hookean) at least 12 cells thick with the pressure
    # split (sim/mpm/pressure.py) instead of explicit MPM where the split's fewer sub-steps pay for
    # its solve by min_cap_gain: nearly incompressible bodies (nu from about 0.47 where the wave sets
    # the step). Only when the solver is explicit (solver.integrator).
    allow_pressure: bool = True
    # Cap E after an elastic impact too: far fewer sub-steps for stiff objects thrown at a wall,
    # but the rebound then differs by pixels (measured 3 px) beyond the bound: predicted_error_px
    # counts them (bulk_cap.rebound_px), the bound does not limit them.
    cap_elastic_impacts: bool = False
    cfl: float = 0.4  # CFL number for predicting sub-steps (the solver's config runs)
    rigid_dt: float = 1e-3  # rigid-body step, s
    restitution: float = 0.6  # rigid-path ground restitution (the material table has none)
    rest_px: float = 0.1  # a frame is still when no particle moved more than this, pixels
    rest_frames: int = 5  # still frames in a row before the remaining frames may be held
    # ... and held only once the motion those frames extrapolate to over the rest of the clip (their
    # fitted geometric decay, ``mpm_run.motion_left_px``) is below this, pixels
    rest_budget_px: float = 0.1
    spread_factor: float = 0.5  # horizontal grid margin for sagging / splashing, object sizes
    ballistic: bool = True  # free flight before the first contact in closed form
    # Flights after a bounce in closed form too (sim/coast.py), while the vibration they leave out
    # fits the bound left over by the plan's own predicted error.
    coast: bool = True
    # The grid moves under a body that bounces or rolls out of the planned region (sim/mpm_run.py,
    # followed_grid); False stops it at the grid's faces, with a warning.
    follow: bool = True
    fit_grid: bool = True  # False: a fixed cube of domain_size on the ground (naive baseline)
    domain_size: float = 1.0  # m, only with fit_grid = False

    def __post_init__(self) -> None:
        check_types(self, "planner setting")
        positive = (
            "bound_px",
            "cells_across",
            "max_cells",
            "particles_per_cell",
            "max_stretched_spacing",
            "cfl",
            "rigid_dt",
        )
        for name in (*positive, "domain_size"):
            if not getattr(self, name) > 0:
                raise ValueError(f"planner setting {name}={getattr(self, name)!r} must be > 0")
        if not self.bulk_wave_ratio > 1.0:
            raise ValueError(f"planner bulk_wave_ratio={self.bulk_wave_ratio!r} must be > 1 (c_p > c_s)")
        if not 0.0 <= self.cap_budget <= 1.0:
            raise ValueError(f"planner cap_budget={self.cap_budget!r} must be in [0, 1]")
        if not self.rest_frames >= 1:
            raise ValueError(
                f"planner rest_frames={self.rest_frames!r} must be >= 1 (a huge value never stops)"
            )
        for name in ("rest_px", "rest_budget_px"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(
                    f"planner setting {name}={getattr(self, name)!r} must be >= 0 (0: never stop early)"
                )
        if not 0.0 <= self.restitution <= 1.0:
            raise ValueError(f"planner restitution={self.restitution!r} must be in [0, 1]")
