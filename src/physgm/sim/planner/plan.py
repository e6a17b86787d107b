"""The plan: what to simulate, what it is predicted to cost and err, and why (its report)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np


@dataclass
class Plan:
    """What to simulate and why.

    Attributes:
        mode: "rigid" or "mpm".
        E_requested, E_used: Young's modulus asked for and simulated (after the caps), Pa.
        nu_requested, nu_used: Poisson ratio asked for and simulated (after the bulk cap).
        predicted_error_px: visual error of this plan relative to full-stiffness MPM, pixels.
        error_terms: named parts of the estimate, pixels.
        px_per_m: pixels per metre at the object for the closest output camera.
        grid_lo, grid_hi: [3] reachable region the grid must hold, m (before boundary margin).
        dx: grid cell size, m.  particle_spacing: m.
        cells_across: grid cells across the object's largest extent: ``PlannerConfig.cells_across``
            times the object's cell over the grid's (less when the region it can reach coarsened
            the grid to fit ``max_cells``).
        substeps_per_frame: predicted (rigid: integration steps per frame).
        predicted_cost: predicted particle-substeps (rigid: body steps).
        rest_px, rest_frames, rest_budget_px: early stop once no particle moved more than rest_px
            pixels per frame for rest_frames frames, and the motion those frames extrapolate to
            over the remaining frames is below rest_budget_px.
        reason: one human-readable sentence.
        walls: contact planes ((n, d), ...) of the scene's still walls, for the rigid path.
        integrator: the MPM solver's integrator the plan runs with (``SolverConfig.integrator``):
            the solver's own, or ``"pressure"`` where the planner took the split
            (``PlannerConfig.allow_pressure``). Unused by the rigid path.
    """

    mode: str
    material: str
    E_requested: float
    E_used: float
    nu_requested: float
    nu_used: float
    predicted_error_px: float
    error_terms: dict[str, float]
    px_per_m: float
    grid_lo: np.ndarray
    grid_hi: np.ndarray
    dx: float
    particle_spacing: float
    cells_across: float
    n_particles: int
    substeps_per_frame: int
    predicted_cost: float
    frame_dt: float
    n_frames: int
    rest_px: float
    rest_frames: int
    rest_budget_px: float
    restitution: float
    reason: str
    alternatives: dict[str, float] = field(default_factory=dict)  # mode -> predicted cost
    walls: list = field(default_factory=list)
    integrator: str = "explicit"

    def summary(self) -> dict:
        """JSON-friendly view (grid as cell counts)."""
        out = {k: v for k, v in asdict(self).items() if not isinstance(v, np.ndarray)}
        out["grid_cells"] = [int(math.ceil(c)) for c in (self.grid_hi - self.grid_lo) / self.dx]
        return out
