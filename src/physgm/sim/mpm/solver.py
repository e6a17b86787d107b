"""The MLS-MPM solver: allocates every array once, then only launches kernels."""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import warp as wp

from physgm.parallel import PairWorker
from physgm.sim.constitutive import MODELS, MaterialParams
from physgm.sim.mpm import kernels as K
from physgm.sim.mpm import particle_ops as ops
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.launches import SubstepLaunches, host_reader
from physgm.sim.mpm.observables import SubstepObservables, SubstepObserver, particle_momentum
from physgm.sim.mpm.particle_store import ParticleStore
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.state import Energy, FrameStats, Particles, ParticleState, Trajectory
from physgm.sim.mpm.stepping import SimulationDiverged, SolverConfig, step_wave_speed
from physgm.sim.mpm.walls import SceneWalls

# Two threads pay off from about 2k particles when each sub-step hands off through Python; when
# the sub-steps are replayed from graphs (the threads meeting at spin barriers) they break even
# near 250 (docs/measurements_sim.md section 16). Below the threshold one thread runs.
_AUTO_THREADS_MIN_PARTICLES = 2_000
_AUTO_THREADS_MIN_PARTICLES_GRAPHS = 500
_STATS_INIT = np.zeros(K.STATS_ROW, dtype=np.float32)
_STATS_INIT[[K.STAT_JMIN, K.STAT_JMAX]] = [1.0e30, -1.0e30]  # running min and max of det F


@dataclass(frozen=True)
class SubstepStats:
    """The G2P kernel's running reductions (columns ``kernels.STAT_*``) since the frame began."""

    max_speed: float  # m/s
    j_min: float  # min det F
    j_max: float  # max det F
    bad: int  # particles with a non-finite state
    escaped: int  # particles newly stopped by the domain clamp
    overrun: int  # particles that left the active grid box (the CFL estimate was exceeded)
    floor_hits: int  # particle sub-steps whose elastic trial det F fell below the model's j_floor

    @classmethod
    def reduce(cls, rows: np.ndarray) -> SubstepStats:  # rows [threads, STATS_ROW], one per thread
        # Python over the few values: numpy's reductions cost more per call than the data here
        # (the solver reads these after every replay). A NaN in a column propagates.
        cols = list(zip(*rows[:, : K.NUM_STATS].tolist(), strict=True))

        def most(xs, pick):
            return math.nan if any(x != x for x in xs) else pick(xs)

        return cls(
            max_speed=math.sqrt(max(most(cols[K.STAT_VMAX], max), 0.0)),  # the kernel keeps |v|^2
            j_min=most(cols[K.STAT_JMIN], min),
            j_max=most(cols[K.STAT_JMAX], max),
            bad=int(sum(cols[K.STAT_BAD])),
            escaped=int(sum(cols[K.STAT_ESCAPED])),
            overrun=int(sum(cols[K.STAT_OVERRUN])),
            floor_hits=int(sum(cols[K.STAT_FLOOR])),
        )

    @property
    def finite(self) -> bool:
        return self.bad == 0 and all(map(math.isfinite, (self.max_speed, self.j_min, self.j_max)))


class GridHook(Protocol):
    """Extension point called after the grid update of every sub-step.

    ``solver.grid_v`` (wp.array4d of ``kernels.vec8``, [bx, by, bz, 64] in 4^3-node blocks, read and
    written through ``grid_layout.load`` and ``store``: node velocity in m/s, mass in kg, velocity
    change of this step; see ``physgm.sim.mpm``) may be modified in place with Warp kernels on
    ``solver.device``; e.g. a rigid collider sets the velocity of the nodes it covers
    and reads the momentum change.
    """

    def apply(self, solver: MPMSolver, dt: float) -> None: ...


def _may_replay(config: SolverConfig, scene: Scene) -> bool:
    """Can this solver's sub-steps run from launch graphs (hooks and observers aside, which can be
    added later)? Not without ``graphs``, not with side walls or periodic axes (``walls`` runs in
    Python every sub-step), and only on the main thread (``_graph_run``)."""
    return (
        config.graphs
        and not (scene.walls or scene.periodic)
        and threading.current_thread() is threading.main_thread()
    )


class MPMSolver:
    """MLS-MPM on a box grid for one or more materials (see physgm.sim.mpm for the full contract).

    Args:
        particles: input particles; ``particles.material`` indexes ``materials``.
        materials: [M] solver parameters.
        grid: background grid; every particle must start inside its free interior. With a ground
            plane whose ``held_depth`` > 0 the solver uses ``grid`` lowered by under a cell
            (``self.grid``) so that a node plane lies that deep below it (``physgm.sim.mpm.boundary``).
        scene: gravity and boundary conditions (default: gravity only).
        config: solver settings.
        device: Warp device ("cpu", "cuda:0", ...).
    """

    def __init__(
        self,
        particles: Particles,
        materials: Sequence[MaterialParams],
        grid: GridSpec,
        scene: Scene | None = None,
        config: SolverConfig | None = None,
        device: str | wp.Device | None = "cpu",
    ) -> None:
        wp.init()
        self.device = wp.get_device(device)
        self.scene = scene or Scene()
        ground = self.scene.ground
        held = ground is not None and ground.held_depth > 0
        self.grid = grid.aligned(ground.height - ground.held_depth * grid.dx) if held else grid
        self.config = config or SolverConfig()
        self.materials = list(materials)
        self.hooks: list[GridHook] = []
        self.observers: list[SubstepObserver] = []  # called after every sub-step (observables.py)
        self._check_inputs(particles)
        n = self.num_particles = len(particles)
        self.time, self.frame, self.escaped = 0.0, 0, 0
        replays = _may_replay(self.config, self.scene)
        least = _AUTO_THREADS_MIN_PARTICLES_GRAPHS if replays else _AUTO_THREADS_MIN_PARTICLES
        auto = 2 if self.device.is_cpu and n >= least and (os.cpu_count() or 1) >= 2 else 1
        self.threads = min(self.config.threads or auto, 2) if self.device.is_cpu else 1
        self._c_max = step_wave_speed(self.materials, self.scene, particles, self.grid.dx)
        self.particles = ParticleStore(particles, self.materials, self.device)
        # The materials whose energy ``energy()`` reports (an integrator that splits the stress
        # between the particles and the grid runs another table in g2p).
        self.energy_table = self.particles.mat_table
        self._launches = SubstepLaunches(
            self.particles, self.grid, self.scene, self.config, self.threads, self.device
        )
        self.arrays = self._launches.arrays
        self._walls = SceneWalls(
            self.scene.walls,
            self.scene.periodic,
            self.grid,
            self.arrays,
            self.config.boundary_cells,
            self.device,
        )
        self._alloc_buffers()
        self._worker = PairWorker() if self.threads == 2 else None
        self.particles.sort(self.grid)
        ps = self.particles
        wp.launch(
            ops.init_stress,
            n,
            [ps.H, ps.mat_table, ps.material, ps.vol0, ps.plastic, ps.stress],
            device=self.device,
        )
        v0 = particles.v if particles.v is not None else np.zeros((n, 3))
        self._vmax = float(np.max(np.linalg.norm(v0, axis=1)))
        self._fit_active(self.stable_dt())

    # ----------------------------------------------------------------------------- setup
    def _check_inputs(self, particles: Particles) -> None:
        if self.grid.num_nodes > self.config.max_grid_nodes:
            raise ValueError(
                f"grid {self.grid.res} has {self.grid.num_nodes:,} nodes "
                f"(~{self.grid.num_nodes * 96 / 1e9:.1f} GB), more than "
                f"max_grid_nodes={self.config.max_grid_nodes:,}; fit the grid to the region the particles "
                "can reach (GridSpec.fit) or use a larger dx"
            )
        if not self.materials or not all(isinstance(m, MaterialParams) for m in self.materials):
            raise ValueError("materials must be a non-empty list of MaterialParams")
        top = int(particles.material.max())
        if top >= len(self.materials):
            raise ValueError(
                f"particle material index {top} but only {len(self.materials)} materials were given"
            )
        lo, hi = self.grid.interior(self.config.boundary_cells)
        outside = ~np.all((particles.x >= lo) & (particles.x <= hi), axis=1)
        if outside.any():
            raise ValueError(
                f"{int(outside.sum())} of {len(particles)} particles start outside the grid interior "
                f"[{lo.round(4).tolist()}, {hi.round(4).tolist()}] m (particle bounds "
                f"{particles.x.min(0).round(4).tolist()} .. {particles.x.max(0).round(4).tolist()}); "
                "enlarge the grid, e.g. GridSpec.fit(lo, hi, dx)"
            )

    def _alloc_buffers(self) -> None:
        """The solver's own arrays; the sub-step's grid arrays belong to the launches (``arrays``)."""
        dev, res = self.device, self.grid.res
        self._energy = wp.zeros(3, dtype=wp.float64, device=dev)
        self._bounds = wp.zeros(2, dtype=wp.vec3, device=dev)
        # Recorded once: a re-fit every cfl_check_every sub-steps is a visible share of a small
        # sub-step's fixed cost (docs/measurements.md).
        self._bounds_launches = [
            wp.launch(ops.reset_bounds, 1, [self._bounds, 0], device=dev, record_cmd=True),
            wp.launch(
                ops.bounds,
                self.num_particles,
                [self.particles.x, 0, self._bounds, 0],
                device=dev,
                record_cmd=True,
            ),
        ]
        self._observed = wp.zeros(4, dtype=wp.float64, device=dev)
        self._dynamic = [*self.particles.dynamic, self.arrays.work, self._walls.impulse]
        self._backup = [wp.empty_like(a) for a in self._dynamic]
        self.active_box = (np.zeros(3, int), np.array(res) - 1)  # node index range grid_update covers
        # What the host reads after every replay
        self._read_bounds = host_reader(self._bounds)
        self._read_stats_rows = host_reader(self.arrays.stats)

    def _fit_active(self, dt: float, stats_read: bool = False) -> None:
        """Limit grid_update to the nodes particles can reach in the next ``cfl_check_every`` steps.

        ``stats_read``: ``self._vmax`` already holds the speed the statistics have seen.
        """
        g, cfg = self.grid, self.config
        self._since_fit = 0
        box = self._launches.replay_bounds()
        if box is None:
            for launch in self._bounds_launches:
                launch.launch()
            box = self._read_bounds().tolist()
        b_lo, b_hi = box
        vmax = self._vmax
        if not stats_read:
            seen = self._read_stats().max_speed
            vmax = max(self._vmax, seen) if math.isfinite(seen) else self._vmax
        reach = 2.0 * vmax * dt * cfg.cfl_check_every + 3.0 * g.dx  # doubled speed, 3-cell stencil pad
        # Three axes in Python floats: numpy's per-call cost on 3-vectors was ~65 us a re-fit, a
        # visible share of a 16-sub-step replay (docs/measurements_sim.md section 24).
        origin, top = [float(o) for o in g.origin], [int(r) - 1 for r in g.res]
        lo = np.array(
            [min(max(math.floor((b_lo[a] - reach - origin[a]) / g.dx), 0), top[a]) for a in range(3)]
        )
        hi = np.array(
            [min(max(math.ceil((b_hi[a] + reach - origin[a]) / g.dx), 0), top[a]) for a in range(3)]
        )
        lo, hi = self._walls.widen_active(lo, hi)
        # Faces on the grid boundary never need a guard: the domain clamp holds particles there.
        inner_lo = [-math.inf if lo[a] == 0 else origin[a] + int(lo[a]) * g.dx + 1.5 * g.dx for a in range(3)]
        inner_hi = [
            math.inf if hi[a] == top[a] else origin[a] + int(hi[a]) * g.dx - 1.5 * g.dx for a in range(3)
        ]
        self.active_box = (lo, hi)
        self._launches.set_active_box(lo, hi, inner_lo, inner_hi)

    # ----------------------------------------------------------------------------- stepping
    def substep(self, dt: float) -> None:
        """One raw MLS-MPM step of ``dt`` seconds (no divergence guard).

        The active grid box is re-fitted every ``cfl_check_every`` calls, so raw stepping loops
        (benchmarks, couplings) stay correct without ``step_frame``.
        """
        if self._since_fit >= self.config.cfl_check_every:
            self._fit_active(dt)
        self._since_fit += 1
        self._launches.set_dt(dt, self.scene.damping)
        self._launches.set_time(self.time)

        before = self._impulses() if self.observers else None
        stamp = self._launches.next_stamp  # the number _launches.run gives this sub-step

        def hooks() -> None:
            self._walls.after_grid_update(stamp, self.active_box)
            for hook in self.hooks:
                hook.apply(self, dt)

        fold = (lambda: self._walls.before_grid_update(stamp)) if self._walls.periodic else None
        self._launches.run(self._worker, hooks, fold)
        if self._walls.periodic:
            self._walls.after_g2p(self.particles.x)
        self.time += dt
        if before is not None:
            self._observe(dt, before)

    def _graph_run(self, dt: float, t_end: float, frame_dt: float) -> int:
        """Sub-steps of ``dt`` the next launch-graph replay can take (0: step in Python).

        A replay takes up to ``cfl_check_every`` sub-steps, exactly those ``_advance`` would take
        one at a time: nothing needs Python between them, and none is the frame's shortened last
        step. The frame's tail (fewer than ``cfl_check_every`` whole steps before its end) is a
        replay too (``launches.run_graph`` replays a count as its binary pieces).
        Only on the main thread: a Warp capture records (instead of running) every launch on its
        device from any thread, so a solver in a worker thread (DPO rollouts run several at once)
        could swallow another's launches; those solvers step in Python.
        """
        if self.hooks or self.observers or not _may_replay(self.config, self.scene):
            return 0
        t, count = self.time, 0
        while count < self.config.cfl_check_every and t_end - t >= dt and t_end - t > 1e-9 * frame_dt:
            t += dt
            count += 1
        return count

    def _substeps_graph(self, dt: float, count: int) -> None:
        """``count`` sub-steps of ``dt`` replayed from a launch graph (``launches.run_graph``)."""
        if self._since_fit + count > self.config.cfl_check_every:
            self._fit_active(dt)
        self._since_fit += count
        self._launches.set_dt(dt, self.scene.damping)
        self._launches.set_time(self.time)
        self._launches.run_graph(count, self._worker)
        for _ in range(count):  # the same float64 sums as stepping one at a time
            self.time += dt

    # ----------------------------------------------------------------------------- observables
    def _impulses(self) -> np.ndarray:
        """Running sums: ground impulse [0:3], face impulse [3:6], face contacts [6], wall impulse [7:10]."""
        w = self.arrays.work.numpy().sum(0)
        return np.concatenate([w[K.WORK_GROUND : K.WORK_FACE_CONTACTS + 1], self._walls.impulse.numpy()])

    def _observe(self, dt: float, before: np.ndarray) -> None:
        d = self._impulses() - before
        self._observed.zero_()
        ps = self.particles
        wp.launch(particle_momentum, self.num_particles, [ps.v, ps.mass, self._observed], device=self.device)
        q = self._observed.numpy()
        obs = SubstepObservables(
            time=self.time,
            dt=dt,
            mass=float(q[3]),
            momentum=q[:3].copy(),
            com_velocity=q[:3] / q[3],
            ground_force=d[0:3] / dt,
            wall_force=d[7:10] / dt,
            face_force=d[3:6] / dt,
            face_contacts=int(round(d[6])),
        )
        for observer in self.observers:
            observer.observe(obs)

    @property
    def face_contacts(self) -> int:
        """Grid-node updates in which the separating walls at the grid faces stopped mass, so far.

        The faces are a safety net, not a boundary condition a scene asks for: a grid that holds
        everywhere the particles go keeps this at 0 (the planner's grids do).
        """
        return int(round(float(self.arrays.work.numpy()[:, K.WORK_FACE_CONTACTS].sum())))

    def stable_dt(self, cfl: float | None = None) -> float:
        """CFL step cfl dx / (c + |v|max) for the current |v|max, s (c: ``step_wave_speed``)."""
        cfl = self.config.cfl if cfl is None else cfl
        return cfl * self.grid.dx / (self._c_max + self._vmax)

    def _read_stats(self) -> SubstepStats:
        return SubstepStats.reduce(self._read_stats_rows()[: self.threads])

    def _advance(self, frame_dt: float, cfl: float) -> tuple[int, float, float, SubstepStats]:
        """Sub-step through one frame; returns (sub-steps, dt_min, dt_max, stats)."""
        cfg = self.config
        self.arrays.stats.assign(np.tile(_STATS_INIT, (2, 1)))
        t_end = self.time + frame_dt
        steps, dt, dt_min, dt_max = 0, 0.0, math.inf, 0.0
        while t_end - self.time > 1e-9 * frame_dt:
            remaining = t_end - self.time
            if steps % cfg.cfl_check_every == 0:
                if steps:
                    s = self._read_stats()
                    if not s.finite or s.overrun or s.floor_hits:
                        break  # rejected below; no point stepping a broken state
                    self._vmax = max(self._vmax, s.max_speed)
                dt_cfl = cfl * self.grid.dx / (self._c_max + self._vmax)
                dt = remaining / math.ceil(remaining / dt_cfl - 1e-9)
                # The statistics were reset at the frame start or read just above.
                self._fit_active(dt, stats_read=True)
            dt = min(dt, remaining)
            count = self._graph_run(dt, t_end, frame_dt) if steps % cfg.cfl_check_every == 0 else 0
            if count:
                self._substeps_graph(dt, count)
            else:
                self.substep(dt)
            steps += count or 1
            dt_min, dt_max = min(dt_min, dt), max(dt_max, dt)
            if steps >= cfg.max_substeps:
                raise SimulationDiverged(
                    f"frame {self.frame} needs more than max_substeps={cfg.max_substeps} sub-steps "
                    f"(dt={dt:.3g} s for frame_dt={frame_dt} s, wave speed {self._c_max:.3g} m/s); "
                    "use a coarser grid, a softer material or the planner's rigid mode"
                )
        return steps, dt_min, dt_max, self._read_stats()

    def step_frame(self, frame_dt: float | None = None) -> FrameStats:
        """Advance one frame with CFL sub-steps; restore and retry with half the CFL on divergence."""
        cfg = self.config
        frame_dt = cfg.frame_dt if frame_dt is None else frame_dt
        if cfg.sort_every and self.frame > 0 and self.frame % cfg.sort_every == 0:
            self.particles.sort(self.grid)
        for src, dst in zip(self._dynamic, self._backup, strict=True):
            wp.copy(dst, src)
        t0, vmax0, cfl, problems = self.time, self._vmax, cfg.cfl, ""
        for attempt in range(cfg.max_retries + 1):
            steps, dt_min, dt_max, s = self._advance(frame_dt, cfl)
            problems = self._problems(s)
            if not problems:
                self.time = t0 + frame_dt
                self.escaped += s.escaped
                self._vmax = s.max_speed
                self.frame += 1
                face_contacts = self.face_contacts
                return FrameStats(
                    self.frame,
                    self.time,
                    steps,
                    dt_min,
                    dt_max,
                    cfl,
                    attempt,
                    s.max_speed,
                    s.j_min,
                    s.j_max,
                    self.escaped,
                    face_contacts,
                )
            for src, dst in zip(self._backup, self._dynamic, strict=True):
                wp.copy(dst, src)
            self._launches.invalidate()  # also clears mass an overrun left outside the active box
            self.time, self._vmax, cfl = t0, vmax0, 0.5 * cfl
        raise SimulationDiverged(
            f"MPM diverged in frame {self.frame} (t={t0:.4g} s): {problems} after {cfg.max_retries} retries "
            f"down to CFL {2 * cfl:.3g}. Materials: "
            + ", ".join(f"{m.model}(E={m.E:.3g} Pa, nu={m.nu}, rho={m.density})" for m in self.materials)
            + f"; dx={self.grid.dx} m. Try a lower cfl, a finer grid, or the planner's rigid mode."
        )

    def _problems(self, s: SubstepStats) -> str:
        cfg = self.config
        if s.floor_hits:  # first: an inversion also moves particles wildly and can turn the state NaN
            floors = ", ".join(f"{m.model} {MODELS[m.model].j_floor:g}" for m in self.materials)
            return (
                f"a step compressed particles below their model's det F floor ({floors}; "
                f"{s.floor_hits} particle sub-steps, smallest det F {s.j_min:.3g})"
            )
        if s.overrun:
            return f"{s.overrun} particles moved faster than the CFL estimate allowed"
        if not s.finite:
            return f"{s.bad} particles reached a non-finite state"
        if s.j_min <= cfg.j_min or s.j_max > cfg.j_max:
            bounds = f"(j_min={cfg.j_min}, j_max={cfg.j_max}]"
            return f"det F reached [{s.j_min:.3g}, {s.j_max:.3g}], outside {bounds}"
        return ""

    def run(self, n_frames: int, record: bool = True) -> Trajectory:
        """Step ``n_frames`` frames; frame 0 of the result is the current state."""
        st = self.state()
        xs, Fs, stats = [st.x], [st.F], []
        for _ in range(n_frames):
            stats.append(self.step_frame())
            if record:
                st = self.state()
                xs.append(st.x)
                Fs.append(st.F)
        return Trajectory(x=np.stack(xs), F=np.stack(Fs), stats=stats)

    # ----------------------------------------------------------------------------- state
    def state(self) -> ParticleState:
        """Copy of the particle state in the caller's order."""
        return self.particles.state()

    def set_velocities(self, v: np.ndarray) -> None:  # v: [P, 3] m/s, caller's order
        v = np.asarray(v, dtype=np.float32)
        if v.shape != (self.num_particles, 3) or not np.isfinite(v).all():
            raise ValueError(f"velocities must be finite with shape [{self.num_particles}, 3], got {v.shape}")
        self.particles.v.assign(v[self.particles.order.numpy()])
        self._launches.invalidate()
        self._vmax = float(np.max(np.linalg.norm(v, axis=1)))
        self._fit_active(self.stable_dt())

    @property
    def grid_v(self) -> wp.array:
        """[bx, by, bz, 64] ``kernels.vec8`` node velocity, mass and velocity change, in 4^3-node
        blocks (``grid_layout``; ``grid_layout.to_dense`` gives [nx, ny, nz, 8]): what grid hooks change."""
        return self.arrays.grid_v

    @property
    def launches(self) -> SubstepLaunches:
        """The recorded kernel launches of one sub-step (tests replay them to check the fused scatter)."""
        return self._launches

    @property
    def driver_work(self) -> float:
        """Energy the velocity boxes (grips, pushers) have put into the system so far, J."""
        return float(self.arrays.work.numpy()[:, K.WORK_DRIVER].sum())

    def energy(self) -> Energy:
        """Kinetic (with the APIC affine part), gravitational and elastic energy, J."""
        ps = self.particles
        self._energy.zero_()
        wp.launch(
            ops.particle_energy,
            self.num_particles,
            [
                ps.x,
                ps.v,
                ps.C,
                ps.H,
                self.energy_table,
                ps.material,
                ps.mass,
                ps.vol0,
                wp.vec3(*self.scene.gravity),
                0.25 * self.grid.dx**2,
                self._energy,
            ],
            device=self.device,
        )
        e = self._energy.numpy()
        return Energy(kinetic=float(e[0]), gravitational=float(e[1]), elastic=float(e[2]))

    def close(self) -> None:
        """Stop the worker thread (also done at garbage collection)."""
        if self._worker is not None:
            self._worker.close()
            self._worker = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass


def run_solver(
    particles: Particles,
    materials: Sequence[MaterialParams],
    grid: GridSpec,
    scene: Scene | None,
    n_frames: int,
    config: SolverConfig | None = None,
    device: str = "cpu",
) -> Trajectory:
    """Build a solver, run ``n_frames`` frames, close it and return the trajectory (frame 0 =
    initial). The engine's one-shot run; Gaussians in, Gaussians out is
    ``physgm.sim.gaussian_trajectory.simulate``."""
    solver = MPMSolver(particles, materials, grid, scene, config, device)
    try:
        return solver.run(n_frames)
    finally:
        solver.close()
