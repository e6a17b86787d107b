"""A wall-clock budget per DPO candidate: plan, predict the seconds, fall back to cheaper plans, or skip.

A stiff candidate needs many MPM sub-steps (the explicit step scales as dx / c_p with
c_p ~ sqrt(E / rho)); one round of DPO rollouts had candidates of 450 s each. Before any solver
step the plan's predicted cost (particle-substeps, ``Plan.predicted_cost``) is turned into
seconds with a measured throughput. When that is over the budget, the planner's cheaper settings
are tried in order (a stiffness cap after elastic impacts, a looser pixel bound), each accepted
only while the planner's own predicted error stays under ``max_error_px``. When none fits, the
candidate is skipped with the reason. A run that passes its deadline anyway (a prediction that
was too optimistic) is cut between frames. Skipped and cut candidates are neither winner nor loser.
"""

from __future__ import annotations

import logging
import statistics
import threading
import time
from dataclasses import dataclass, field

from physgm.physics.materials import PhysicsSpec
from physgm.setting_types import check_types

log = logging.getLogger("physgm.train.rollout")


def _default_fallbacks() -> list[dict]:
    return [
        {"cap_elastic_impacts": True},  # the cap the planner already uses elsewhere, with its error
        {"cap_elastic_impacts": True, "bound_px": 2.0},  # a 4x looser bound: a lower cap
    ]


@dataclass
class BudgetConfig:
    """Time budget of one candidate (``stage.rollout.budget``)."""

    max_seconds: float | None = (
        30.0  # wall clock per candidate (plan + simulate + render + score); None: none
    )
    # MPM particle-substeps per second, to turn a plan's predicted cost into seconds: the prior, and
    # with ``calibrate`` the median of this process's last finished MPM rollouts replaces it (a shared
    # host's throughput moves 10x with its load; docs/model.md, "Bounded rollouts").
    throughput: float = 1.0e6
    calibrate: bool = True
    fallbacks: list[dict] = field(default_factory=_default_fallbacks)  # planner overrides, cheapest last
    max_error_px: float = 4.0  # a fallback whose predicted error is larger is not used
    reserve_seconds: float = 2.0  # kept for rendering and scoring after the simulation

    def __post_init__(self) -> None:
        check_types(self, "rollout budget setting")
        if self.max_seconds is not None and not self.max_seconds > self.reserve_seconds >= 0:
            raise ValueError(
                f"budget.max_seconds={self.max_seconds} must exceed budget.reserve_seconds="
                f"{self.reserve_seconds} >= 0 (or be null for no budget)"
            )
        if not self.throughput > 0 or not self.max_error_px > 0:
            raise ValueError(
                f"budget.throughput and budget.max_error_px must be > 0, got {self.throughput}, "
                f"{self.max_error_px}"
            )


@dataclass
class BoundedRun:
    """The outcome of one budgeted simulation."""

    trajectory: object | None  # physgm.sim.gaussian_trajectory.GaussianTrajectory; None when skipped
    planner: dict  # the planner overrides that ran (the base settings plus a fallback's)
    fallback: int  # -1: the plan as asked; i: ``BudgetConfig.fallbacks[i]``
    predicted_seconds: float
    predicted_error_px: float  # the plan's error against full-stiffness MPM, pixels
    skipped: str | None = None  # why nothing (or not everything) was simulated


class ThroughputEstimate:
    """MPM particle-substeps per second seen in this process: the median of the last ``window`` runs."""

    def __init__(self, window: int = 8) -> None:
        self.window, self._seen, self._lock = window, [], threading.Lock()

    def add(self, trajectory) -> None:
        """Record a finished MPM run (rigid runs say nothing about the MPM's speed)."""
        seconds = trajectory.seconds - trajectory.plan_seconds
        if trajectory.plan.mode == "mpm" and trajectory.substeps > 0 and seconds > 0:
            with self._lock:
                self._seen = [*self._seen, trajectory.substeps * trajectory.plan.n_particles / seconds]
                self._seen = self._seen[-self.window :]

    def get(self, prior: float) -> float:
        with self._lock:
            return statistics.median(self._seen) if self._seen else prior

    def clear(self) -> None:
        with self._lock:
            self._seen = []


THROUGHPUT = ThroughputEstimate()  # this process's observations (rollout workers are threads)


def bounded_simulate(
    gaussians,
    physics: PhysicsSpec,
    scene: str,
    camera,
    n_frames: int,
    planner: dict,
    solver,
    scene_overrides: dict,
    device: str,
    budget: BudgetConfig,
    start: float | None = None,
) -> BoundedRun:
    """``physgm.sim.gaussian_trajectory.simulate`` within ``budget`` (seconds counted from ``start``)."""
    from physgm.sim.gaussian_trajectory import prepare_simulation, run_prepared
    from physgm.sim.mpm_run import SimulationBudgetExceeded

    start = time.perf_counter() if start is None else start
    if budget.max_seconds is None:
        prepared = prepare_simulation(
            gaussians, physics, scene, camera, n_frames, planner, solver, scene_overrides
        )
        traj = run_prepared(prepared, device)
        return BoundedRun(traj, planner, -1, 0.0, prepared.plan.predicted_error_px)
    deadline = start + budget.max_seconds - budget.reserve_seconds
    throughput = THROUGHPUT.get(budget.throughput) if budget.calibrate else budget.throughput
    tried = []
    for i, extra in enumerate([{}, *budget.fallbacks]):
        over = {**planner, **extra}
        prepared = prepare_simulation(
            gaussians, physics, scene, camera, n_frames, over, solver, scene_overrides
        )
        seconds = prepared.predicted_seconds(throughput)
        error = prepared.plan.predicted_error_px
        tried.append(f"{_label(extra)}: {seconds:.0f} s, {error:.2g} px")
        if i > 0 and error > budget.max_error_px:
            break  # the fallbacks only get cheaper and less exact from here
        if time.perf_counter() + seconds <= deadline:
            try:
                traj = run_prepared(prepared, device, deadline)
            except SimulationBudgetExceeded as err:
                reason = f"{err} ({budget.max_seconds:.0f} s budget; predicted {seconds:.0f} s)"
                log.warning("candidate %s E=%.3g Pa cut: %s", physics.material, physics.E, reason)
                return BoundedRun(None, over, i - 1, seconds, error, f"cut: {reason}")
            THROUGHPUT.add(traj)
            return BoundedRun(traj, over, i - 1, seconds, error)
    reason = (
        f"predicted over the {budget.max_seconds:.0f} s budget with every plan tried "
        f"({'; '.join(tried)}; at {throughput:.3g} particle-substeps/s; fallbacks need <= "
        f"{budget.max_error_px} px)"
    )
    log.warning("candidate %s E=%.3g Pa skipped: %s", physics.material, physics.E, reason)
    return BoundedRun(None, planner, -1, seconds, error, f"skipped: {reason}")


def _label(extra: dict) -> str:
    return "as planned" if not extra else ", ".join(f"{k}={v}" for k, v in extra.items())
