"""The MPM part of ``simulate``: free flight in closed form where nothing but gravity acts, the
Warp solver in between, and early stop once everything is still.

Frames before the first contact are the exact ballistic prefix (``ballistic_frames``: uniform
gravity does not deform a body moving as a whole); flights after a bounce are computed in closed
form while the vibration they leave out fits the pixel bound (``physgm.sim.coast``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from physgm.sim.coast import fall_time, next_flight
from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.integrators import make_solver
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.state import Particles
from physgm.sim.mpm.stepping import SolverConfig
from physgm.sim.planner import Plan
from physgm.sim.sampling import ParticleSample


def ballistic_frames(
    x: np.ndarray, v0: np.ndarray, scene: Scene, frame_dt: float, n_frames: int, gap: float
) -> int:
    """Number of leading frames (incl. frame 0) during which the object is in free flight.

    Only for a body moving as a whole (uniform v0), with nothing prescribed, while its lowest
    point stays ``gap`` (m) above the ground: there uniform gravity leaves it undeformed.
    """
    if scene.ground is None or scene.boxes or len(x) == 0 or np.ptp(v0, axis=0).max() > 1e-9:
        return 1
    height = x[:, 2].min() - scene.ground.height - gap
    gz = float(scene.gravity[2])
    if height <= 0 or gz >= 0:
        return 1
    t_hit = fall_time(float(height), float(v0[0, 2]), gz)
    return int(min(n_frames, max(1, math.floor(t_hit / frame_dt) + 1)))


class SimulationBudgetExceeded(RuntimeError):
    """The MPM run passed its wall-clock deadline; raised between frames, nothing is returned."""

    def __init__(self, frames_done: int, n_frames: int) -> None:
        super().__init__(f"cut at frame {frames_done} of {n_frames}: past its wall-clock deadline")
        self.frames_done, self.n_frames = frames_done, n_frames


@dataclass
class MPMRun:
    """What ``run_mpm`` returns: per-frame state and how each frame was made."""

    x: np.ndarray  # [T, P, 3] m
    F: np.ndarray  # [T, P, 3, 3]
    substeps: int
    rest_frame: int | None
    ballistic_frames: int  # leading frames in closed form (the first fall)
    coasted_frames: int  # later frames in closed form (flights after a bounce, sim/coast.py)
    face_contacts: int
    coast_predicted_px: float = 0.0  # the largest predicted error of a coasted flight, pixels


def motion_left_px(window: list[float], frames_left: int) -> float:
    """The motion a settling body still has in it: the largest per-frame particle motion of the
    last frames (``window``, pixels, oldest first) continued over ``frames_left`` frames as the
    geometric decay fitted to them (least squares on their logarithms), pixels.

    Holding the frames from here on moves no particle by more than this if the decay goes on; a
    window that does not decay (a slide at constant speed, a body starting to tip) continues at its
    last frame's motion, which the budget then refuses unless few frames are left.
    """
    m = np.maximum(np.asarray(window, dtype=np.float64), 1e-12)
    last = float(m[-1])
    if len(m) < 2:
        return last * frames_left
    steps = np.arange(len(m), dtype=np.float64)
    ratio = math.exp(float(np.polyfit(steps, np.log(m), 1)[0]))
    if ratio >= 1.0:
        return last * frames_left
    return last * ratio * (1.0 - ratio**frames_left) / (1.0 - ratio)


def _can_coast(scene: Scene, budget_px: float) -> bool:
    """Flights may be coasted: there is a pixel budget and only gravity and the ground act
    (nothing prescribed, no walls, no drag)."""
    return (
        budget_px > 0.0
        and scene.ground is not None
        and not (scene.boxes or scene.walls or scene.periodic)
        and scene.damping == 0.0
    )


def run_mpm(
    plan: Plan,
    material: MaterialParams,
    scene: Scene,
    x0: np.ndarray,
    v0: np.ndarray,
    sample: ParticleSample,
    solver_cfg: SolverConfig,
    device: str,
    ballistic: bool = True,
    deadline: float | None = None,
    coast_budget_px: float = 0.0,
) -> MPMRun:
    """MPM with a ballistic prefix, flights after a bounce in closed form, and early stop.

    ``coast_budget_px``: pixels a coasted flight's vibration may move a point by (0: never coast).
    """
    T, frame_dt, n = plan.n_frames, plan.frame_dt, len(x0)
    xs = np.empty((T, n, 3), np.float32)
    Fs = np.empty((T, n, 3, 3), np.float32)
    g = np.asarray(scene.gravity, dtype=np.float64)
    k0 = ballistic_frames(x0, v0, scene, frame_dt, T, gap=3 * plan.dx) if ballistic else 1
    for k in range(k0):
        t = k * frame_dt
        xs[k] = x0 + v0 * t + 0.5 * g * t * t
        Fs[k] = np.eye(3, dtype=np.float32)
    if k0 == T:
        return MPMRun(xs, Fs, 0, None, k0, 0, 0)
    t0 = (k0 - 1) * frame_dt
    grid = GridSpec.fit(plan.grid_lo, plan.grid_hi, plan.dx, margin_cells=solver_cfg.boundary_cells)
    volume = sample.volume.cpu().numpy()
    mass = volume.astype(np.float64) * material.density
    particles = Particles(x=xs[k0 - 1], volume=volume, material=0, v=v0 + g * t0)
    solver = make_solver(particles, [material], grid, scene, solver_cfg, device)
    coast_ok = _can_coast(scene, coast_budget_px)
    substeps, moved, rest_frame, coasted, faces, coast_px = 0, [], None, 0, 0, 0.0
    try:
        k = k0
        while k < T:
            if deadline is not None and time.perf_counter() > deadline:
                raise SimulationBudgetExceeded(k, T)
            stats = solver.step_frame()
            substeps += stats.substeps
            state = solver.state()
            xs[k], Fs[k] = state.x, state.F
            # Still = no particle moved a visible amount in each of the last rest_frames frames,
            # and the motion they extrapolate to over the frames left (a slow creep) stays under
            # the budget. Instantaneous speeds are not used: MPM particles jitter at high
            # frequency with invisible amplitude long after the object has settled.
            moved.append(float(np.linalg.norm(xs[k] - xs[k - 1], axis=1).max()) * plan.px_per_m)
            window = moved[-plan.rest_frames :]
            if (
                len(window) == plan.rest_frames
                and max(window) < plan.rest_px
                and motion_left_px(window, T - 1 - k) < plan.rest_budget_px
            ):
                rest_frame = k + 1
                xs[k + 1 :], Fs[k + 1 :] = xs[k], Fs[k]
                break
            # A plane lowered under a body that started in the ground would move on a restart.
            flight = (
                next_flight(
                    state, mass, volume, material, scene, frame_dt, T - 1 - k, 3 * plan.dx,
                    plan.px_per_m, coast_budget_px,
                )
                if coast_ok and solver.launches.contact_height == scene.ground.height
                else None
            )  # fmt: skip
            if flight is not None:
                xs[k + 1 : k + 1 + flight.frames], Fs[k + 1 : k + 1 + flight.frames] = flight.x, flight.F
                faces += solver.face_contacts
                solver.close()
                resume = Particles(
                    x=flight.x[-1],
                    volume=volume,
                    material=0,
                    v=flight.v,
                    F=flight.F[-1],
                    C=flight.C,
                    plastic=state.plastic,
                )
                solver = make_solver(resume, [material], grid, scene, solver_cfg, device)
                coasted += flight.frames
                coast_px = max(coast_px, flight.predicted_px)
                k += flight.frames
                moved = []
            k += 1
        faces += solver.face_contacts
    finally:
        solver.close()
    return MPMRun(xs, Fs, substeps, rest_frame, k0, coasted, faces, coast_px)
