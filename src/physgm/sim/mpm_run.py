"""The MPM part of ``simulate``: free flight in closed form where nothing but gravity acts, the
Warp solver in between, and early stop once everything is still.

Frames before the first contact are the exact ballistic prefix (``ballistic_frames``: uniform
gravity does not deform a body moving as a whole); flights after a bounce are computed in closed
form while the vibration they leave out fits the pixel bound (``physgm.sim.coast``). A body that
bounces or rolls further than the planner's region, or rebounds above a grid the planner cut short
of a tall drop, is followed: the grid moves under it by whole cells (``followed_grid``) instead of
stopping it at its faces, and a frame whose body met the faces anyway (a landing's splash) is run
again from its start on a grid that holds it (``_splash_grid``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from physgm.sim.coast import ballistic_frames, next_flight
from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.integrators import make_solver
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.state import Particles
from physgm.sim.mpm.stepping import SolverConfig
from physgm.sim.planner import Plan
from physgm.sim.sampling import ParticleSample


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
    grid_moves: int = 0  # times the grid moved under the body (``followed_grid``), retried frames included


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
    floor: float | None = None,  # lowest origin z (m) the grid may take; None: z stays as planned
    gravity: float = 0.0,  # m/s^2, downward: what a frame adds to a vertical reach
) -> GridSpec | None:
    """``grid`` moved under the body by whole cells along x and y (and z above ``floor``), and
    widened where the body no longer fits, once the next frame could carry a particle out of the
    grid's free interior, towards the faces' walls; None while the body stays inside it.

    "Could" is the fastest particle's speed along the axis kept for a frame, plus what gravity
    adds along z (the free interior already keeps a particle's stencil off the walls), so a body
    the planned grid holds does not move it. The moved grid centres the body with that reach on
    each side; its nodes keep their lattice, so the body is discretised as before.
    An axis that must widen widens by at least ``room`` of its width (x and y), so a body that keeps
    spreading (sand after a landing) moves the grid every few frames instead of every frame: each
    move builds a new solver and records its launch graphs anew.

    Along z the grid moves only with a ``floor``: the planned grid's own origin, whose bottom holds
    the ground. A grid the planner cut short of a tall drop's height (``planner.domain``) rises with
    a rebound and comes back down to it; at the floor, the ground holds the body. It goes lower only
    when a move must hold particles a hard landing drove through the floor's interior (a solver is
    built only around particles inside its interior).
    """
    dx, origin, res = grid.dx, np.asarray(grid.origin, dtype=np.float64), np.asarray(grid.res)
    free_lo, free_hi = grid.interior(margin_cells + 1)
    lo, hi = x.min(0), x.max(0)
    reach = np.abs(v).max(0) * frame_dt
    new_origin, new_res = origin.copy(), res.copy()
    moves = False
    if np.any(lo[:2] - reach[:2] < free_lo[:2]) or np.any(hi[:2] + reach[:2] > free_hi[:2]):
        # Cells to add so the body and its reach fit the free interior, an even number (both sides).
        missing = (hi[:2] - lo[:2] + 2.0 * reach[:2]) - (free_hi[:2] - free_lo[:2])
        add = 2 * np.ceil(np.maximum(missing, 0.0) / (2.0 * dx) - 1e-9).astype(int)
        add = np.where(add > 0, np.maximum(add, 2 * np.ceil(0.5 * room * res[:2]).astype(int)), 0)
        new_res[:2] = res[:2] + add
        centre = origin[:2] + 0.5 * (new_res[:2] - 1) * dx  # of the widened grid before it moves
        new_origin[:2] += np.round((0.5 * (lo[:2] + hi[:2]) - centre) / dx) * dx
        moves = True
    if floor is not None:
        reach_z = reach[2] + 0.5 * abs(gravity) * frame_dt**2  # gravity's share of a frame too
        vertical = _followed_z(origin[2], res[2], lo[2], hi[2], reach_z, floor, dx, margin_cells + 1)
        if vertical is not None:
            new_origin[2], new_res[2] = vertical
            moves = True
    if not moves:
        return None
    return GridSpec(tuple(new_origin), dx, tuple(int(n) for n in new_res))


def _followed_z(
    origin: float, nodes: int, lo: float, hi: float, reach: float, floor: float, dx: float, pad: int
) -> tuple[float, int] | None:
    """(origin z, nodes along z) of a grid that holds the body [lo, hi] (m) and its vertical reach,
    on the lattice of ``floor``, or None when the grid ``origin``, ``nodes`` does.

    Below the floor grid's free interior (``pad`` cells up: the ground) the ground, not the grid,
    stops the body, so the reach below counts only above it. A particle a hard landing drove more
    than a cell under it, outside the interior a solver is built around, is held by a lower grid."""
    ground = floor + pad * dx
    need_lo = lo if lo < ground - dx else max(lo - reach, ground)
    need_hi = hi + reach
    if origin + pad * dx <= need_lo and origin + (nodes - 1 - pad) * dx >= need_hi:
        return None
    nodes = max(nodes, math.ceil((need_hi - need_lo) / dx - 1e-9) + 2 * pad + 2)
    highest = math.floor((need_lo - floor) / dx + 1e-9) - pad  # cells above the floor that hold need_lo
    lowest = math.ceil((need_hi - floor) / dx - 1e-9) - (nodes - 1 - pad)  # ... and need_hi
    cells = min(max(round(0.5 * (highest + lowest)), lowest, 0), highest)
    return floor + cells * dx, nodes


# The share of its width a grid axis that must widen under a spreading body widens by at least
# (``followed_grid``'s room): a sheet of sand moves its grid every few frames instead of every
# frame (docs/measurements_sim.md section 33). A wider grid costs a sub-step only the blocks no
# particle reaches, and on the CPU its node arrays take memory only where particles go.
GRID_ROOM = 0.25


def _moved_grid(
    grid: GridSpec,
    x: np.ndarray,
    v: np.ndarray,
    frame_dt: float,
    cfg: SolverConfig,
    floor: float | None = None,
    gravity: float = 0.0,
) -> GridSpec | None:
    """``followed_grid`` with room to spread into, or without it past the solver's node cap; past
    the cap either way the faces' walls stay, as before."""
    for room in (GRID_ROOM, 0.0):
        moved = followed_grid(grid, x, v, frame_dt, cfg.boundary_cells, room, floor, gravity)
        if moved is None or moved.num_nodes <= cfg.max_grid_nodes:
            return moved
    return None


# Times one frame is run again on a wider grid after the body met the faces' walls (``_splash_grid``).
FACE_RETRIES = 2


def _splash_grid(
    grid: GridSpec,
    start,  # ParticleState at the frame's start
    end,  # ParticleState at its end, on ``grid``
    frame_dt: float,
    cfg: SolverConfig,
    floor: float | None,
    gravity: float,
) -> GridSpec | None:
    """A grid that holds what a frame did, for running it again, or None when none can (the node
    cap, or a grid that already holds it).

    ``followed_grid`` reads a frame's reach from the speeds at its start, and a landing's splash
    starts within the frame: just before it the body moves down and not sideways, so the grid it
    keeps meets the splash at its side faces (docs/measurements_sim.md section 41). The frame's
    start and end together, positions and speeds, give the reach the splash took."""
    x = np.concatenate([start.x, end.x])
    v = np.concatenate([start.v, end.v])
    return _moved_grid(grid, x, v, frame_dt, cfg, floor, gravity)


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
    return budget_px > 0.0 and scene.ground is not None and scene.grid_free and scene.damping == 0.0


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
    scenes without velocity boxes, side walls or periodic axes), and run a frame whose body met the
    grid's faces again on a wider grid (``_splash_grid``); False stops it at the grid's faces.
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
    follow_ok = follow and scene.grid_free
    # Along z the grid follows above the planned one, whose bottom holds the ground.
    floor = solver.grid.origin[2] if scene.ground is not None else None
    fall = max(-float(g[2]), 0.0)
    substeps, moved, rest_frame, coasted, faces, coast_px, moves = 0, [], None, 0, 0, 0.0, 0
    tries = 0
    state = solver.state()
    try:
        k = k0
        while k < T:
            if deadline is not None and time.perf_counter() > deadline:
                raise SimulationBudgetExceeded(k, T)
            start, faces_before = state, solver.face_contacts
            stats = solver.step_frame()
            substeps += stats.substeps
            state = solver.state()
            wider = None
            if follow_ok and tries < FACE_RETRIES and solver.face_contacts > faces_before:
                wider = _splash_grid(solver.grid, start, state, frame_dt, solver_cfg, floor, fall)
            if wider is not None:  # the frame again from its start, on a grid that holds it
                faces += faces_before
                resume, continued = _resumed(solver, start, volume, scene)
                solver.close()
                solver = make_solver(resume, [material], wider, continued, solver_cfg, device)
                state, tries, moves = start, tries + 1, moves + 1
                continue
            tries = 0
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
            more = k + 1 < T  # frames left to simulate (a flight may have reached the clip's end)
            moving = None
            if more and follow_ok:
                moving = _moved_grid(solver.grid, state.x, state.v, frame_dt, solver_cfg, floor, fall)
            if more and (flight is not None or moving is not None):  # a new solver continues from ``state``
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
