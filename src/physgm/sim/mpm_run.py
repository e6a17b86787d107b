"""The MPM part of ``simulate``: free flight in closed form where nothing but gravity acts, the
Warp solver in between, and early stop once everything is still.

Frames before the first contact are the exact ballistic prefix (``ballistic_frames``: uniform
gravity does not deform a body moving as a whole); flights after a bounce are computed in closed
form while the vibration they leave out fits the pixel bound (``physgm.sim.coast``). A body that
bounces or rolls further than the planner's region is followed: the grid moves under it by whole
cells (``followed_grid``) instead of stopping it at its faces.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

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
    grid_moves: int = 0  # times the grid moved under the body (``followed_grid``)


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


def followed_grid(
    grid: GridSpec,
    x: np.ndarray,  # [P, 3] particles, m
    v: np.ndarray,  # [P, 3] their velocities, m/s
    frame_dt: float,  # s
    margin_cells: int,  # the solver's ``boundary_cells``
    room: float = 0.0,  # share of its width an axis that must widen widens by at least
) -> GridSpec | None:
    """``grid`` moved under the body by whole cells along x and y, and widened where the body no
    longer fits, once the next frame could carry a particle out of the grid's free interior,
    towards the faces' walls; None while the body stays inside it.

    "Could" is the fastest particle's horizontal speed kept for a frame (the free interior already
    keeps a particle's stencil off the walls), so a body the planned grid holds does not move it.
    The moved grid centres the body with that reach on each side; its nodes keep their lattice, so
    the body is discretised as before. z is left as planned: the ground below, the highest rise above.
    An axis that must widen widens by at least ``room`` of its width, so a body that keeps spreading
    (sand after a landing) moves the grid every few frames instead of every frame: each move
    builds a new solver and records its launch graphs anew.
    """
    dx, origin, res = grid.dx, np.asarray(grid.origin, dtype=np.float64), np.asarray(grid.res)
    free_lo, free_hi = grid.interior(margin_cells + 1)
    lo, hi = x[:, :2].min(0), x[:, :2].max(0)
    reach = np.abs(v[:, :2]).max(0) * frame_dt
    if np.all(lo - reach >= free_lo[:2]) and np.all(hi + reach <= free_hi[:2]):
        return None
    # Cells to add so the body and its reach fit the free interior, an even number (both sides).
    missing = (hi - lo + 2.0 * reach) - (free_hi[:2] - free_lo[:2])
    add = 2 * np.ceil(np.maximum(missing, 0.0) / (2.0 * dx) - 1e-9).astype(int)
    add = np.where(add > 0, np.maximum(add, 2 * np.ceil(0.5 * room * res[:2]).astype(int)), 0)
    nodes = res[:2] + add
    centre = origin[:2] + 0.5 * (nodes - 1) * dx  # of the widened grid before it moves
    shift = np.round((0.5 * (lo + hi) - centre) / dx)
    new_origin = origin.copy()
    new_origin[:2] += shift * dx
    return GridSpec(tuple(new_origin), dx, (int(nodes[0]), int(nodes[1]), int(res[2])))


# The share of its width a grid axis that must widen under a spreading body widens by at least
# (``followed_grid``'s room): a sheet of sand moves its grid every few frames instead of every
# frame (docs/measurements_sim.md section 33). A wider grid costs a sub-step only the blocks no
# particle reaches, and on the CPU its node arrays take memory only where particles go.
GRID_ROOM = 0.25


def _moved_grid(
    grid: GridSpec, x: np.ndarray, v: np.ndarray, frame_dt: float, cfg: SolverConfig
) -> GridSpec | None:
    """``followed_grid`` with room to spread into, or without it past the solver's node cap; past
    the cap either way the faces' walls stay, as before."""
    for room in (GRID_ROOM, 0.0):
        moved = followed_grid(grid, x, v, frame_dt, cfg.boundary_cells, room)
        if moved is None or moved.num_nodes <= cfg.max_grid_nodes:
            return moved
    return None


def _unbound(scene: Scene) -> bool:
    """Nothing in the scene is tied to the grid's place or the solver's time, so a solver may be
    rebuilt elsewhere mid-run (after a coasted flight, on a moved grid): velocity boxes keep a
    schedule a rebuilt solver would restart; side walls and periodic axes are the grid's."""
    return not (scene.boxes or scene.walls or scene.periodic)


def _resumed(solver, state, volume: np.ndarray, scene: Scene) -> tuple[Particles, Scene]:
    """The particles and scene of a solver that continues ``solver``'s run from ``state`` (after a
    coasted flight, or on a moved grid): the contact plane stays where the first solver put it (a
    body resting on the contact springs would otherwise lower it, ``GroundPlane.contact_height``)."""
    resume = Particles(
        x=state.x, volume=volume, material=0, v=state.v, F=state.F, C=state.C, plastic=state.plastic
    )
    ground = scene.ground
    if ground is not None and ground.on_particles:
        scene = replace(scene, ground=replace(ground, contact_height=solver.launches.contact_height))
    return resume, scene


def _can_coast(scene: Scene, budget_px: float) -> bool:
    """Flights may be coasted: there is a pixel budget and only gravity and the ground act
    (nothing prescribed, no walls, no drag)."""
    return budget_px > 0.0 and scene.ground is not None and _unbound(scene) and scene.damping == 0.0


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
    follow: bool = True,
    on_frame: Callable[[int, int], None] | None = None,
) -> MPMRun:
    """MPM with a ballistic prefix, flights after a bounce in closed form, and early stop.

    ``coast_budget_px``: pixels a coasted flight's vibration may move a point by (0: never coast).
    ``follow``: move the grid under a body that leaves the planned region (``followed_grid``;
    scenes without velocity boxes, side walls or periodic axes); False stops it at the grid's faces.
    ``on_frame(frames, substeps)``: called whenever more of the clip is done (the closed-form
    prefix, each simulated frame, a coasted flight, the held frames after rest) with the frames of
    the clip done so far and the sub-steps taken; ``simulate.py``'s progress bar.
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
    report = on_frame if on_frame is not None else (lambda frames, substeps: None)
    report(k0, 0)
    if k0 == T:
        return MPMRun(xs, Fs, 0, None, k0, 0, 0)
    t0 = (k0 - 1) * frame_dt
    grid = GridSpec.fit(plan.grid_lo, plan.grid_hi, plan.dx, margin_cells=solver_cfg.boundary_cells)
    volume = sample.volume.cpu().numpy()
    mass = volume.astype(np.float64) * material.density
    particles = Particles(x=xs[k0 - 1], volume=volume, material=0, v=v0 + g * t0)
    solver = make_solver(particles, [material], grid, scene, solver_cfg, device)
    coast_ok = _can_coast(scene, coast_budget_px)
    follow_ok = follow and _unbound(scene)
    substeps, moved, rest_frame, coasted, faces, coast_px, moves = 0, [], None, 0, 0, 0.0, 0
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
                report(T, substeps)
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
                state = replace(state, x=flight.x[-1], v=flight.v, F=flight.F[-1], C=flight.C)
                coasted += flight.frames
                coast_px = max(coast_px, flight.predicted_px)
                k += flight.frames
                moved = []
            follows = follow_ok and k + 1 < T
            moving = _moved_grid(solver.grid, state.x, state.v, frame_dt, solver_cfg) if follows else None
            if flight is not None or moving is not None:  # a new solver continues from ``state``
                faces += solver.face_contacts
                grid = solver.grid
                if moving is not None:
                    grid, moves = moving, moves + 1
                resume, continued = _resumed(solver, state, volume, scene)
                solver.close()
                solver = make_solver(resume, [material], grid, continued, solver_cfg, device)
            k += 1
            report(k, substeps)
        faces += solver.face_contacts
    finally:
        solver.close()
    return MPMRun(xs, Fs, substeps, rest_frame, k0, coasted, faces, coast_px, moves)
