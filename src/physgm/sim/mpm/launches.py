"""The recorded kernel launches of one MPM sub-step, per worker thread; they own the grid arrays.

In steady state a sub-step is grid_update then g2p, which also scatters the particles for the
next sub-step (``kernels``); p2g runs only when the accumulators were invalidated.

Recording once (``wp.launch(..., record_cmd=True)``) and replaying keeps the Python cost of a
sub-step to a few launches. The values that change between sub-steps (dt, time, damping, the
block stamp, the active box) are read by the kernels from one device array (``substep_params``),
so the launches never change; with nothing to run in Python between them (no grid hooks, side
walls or observers), the solver replays whole runs of sub-steps from a graph captured once
(``run_graph``), which costs about a microsecond per launch instead of ~5-10. With two CPU
threads each replays a graph of its own, and the two meet at ``spin_barrier`` launches instead of
handing off through Python every sub-step.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from physgm.sim.constitutive import MODELS
from physgm.sim.mpm import kernels as K
from physgm.sim.mpm import particle_ops as ops
from physgm.sim.mpm.boundary import no_ground
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.grid_arrays import GridArrays
from physgm.sim.mpm.grid_layout import block_res
from physgm.sim.mpm.particle_ground import ground_stiffness, pack_contact, raised_modulus
from physgm.sim.mpm.particle_store import ParticleStore
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.spin_barrier import LIMIT_CYCLES, YIELD_AFTER_CYCLES, abandoned, barrier, new_counter
from physgm.sim.mpm.stepping import SolverConfig
from physgm.sim.mpm.substep_params import SubstepParams, advance_clock
from physgm.sim.mpm.surface_friction import surface_friction
from physgm.warp_runtime import ensure_loaded


def host_reader(a: wp.array):
    """A function returning what the host reads of ``a``: on the CPU one numpy view made here (making
    a view costs ~5 us, a visible share of the host's work between two replays), elsewhere a copy."""
    if a.device.is_cpu:
        view = a.numpy()
        return lambda: view
    return a.numpy


class SubstepLaunches:
    """p2g and g2p launches for ``threads`` particle slices, one grid_update, the surface friction
    and the clock; ``run`` launches one sub-step from Python, ``run_graph`` replays several.

    Args:
        particles: the solver's particle arrays (the launches read and write them in place).
        grid: the grid the solver runs on.
        scene: gravity, ground and velocity boxes (side walls and periodic axes are ``walls.py``).
        config: solver settings (``flip``, ``boundary_cells``).
        threads: 1 or 2 particle slices, each with its own accumulator.
        device: Warp device.
    """

    def __init__(
        self,
        particles: ParticleStore,
        grid: GridSpec,
        scene: Scene,
        config: SolverConfig,
        threads: int,
        device,
    ) -> None:
        self.arrays = GridArrays.allocate(grid.res, scene.boxes, device)
        # What changes between sub-steps, one row per thread (``substep_params``).
        self.params = wp.zeros(threads, dtype=SubstepParams, device=device)
        # The host writes ``params`` through numpy field views (building Warp vectors costs ~10 us
        # each): on the CPU straight into the array, on a GPU into a host copy sent when it changed.
        self._staging = self.params if self.params.device.is_cpu else wp.zeros_like(self.params, device="cpu")
        view = self._staging.numpy()
        self._field = {name: view[name] for name in view.dtype.names}
        self._field["damping"][:] = 1.0
        self._t = 0.0  # s, the device's t at the start of the next sub-step
        # The scatter stamps the blocks it reaches with the number of the sub-step that consumes it,
        # so stale stamps never match and nothing needs clearing; the first sub-step is number 1.
        self._stamp = 1
        self._dirty = True
        self.device = device
        self._record(particles, grid, scene, config, threads, device)
        self._dt = None
        self._graphs: dict[int, list[wp.Graph]] = {}  # per thread, captured runs of n sub-steps
        self.replayed = 0  # sub-steps run from a graph so far
        self.scattered = False  # the accumulators hold the current particles' scatter
        # An integrator's own recorded launches (``set_grid_stage``), one per thread with a fresh
        # scatter and one per thread after each grid update; ``on_invalidate``: what it clears
        # when the particle state is replaced.
        self.fresh: list = []
        self.post_grid: list = []
        self.on_invalidate: list = []

    def _record(
        self, ps: ParticleStore, g: GridSpec, scene: Scene, cfg: SolverConfig, threads: int, dev
    ) -> None:
        a = self.arrays
        origin = wp.vec3(*g.origin)
        lo, hi = g.interior(1)
        if scene.ground is None:
            ground = no_ground()
        elif scene.ground.on_particles:
            ground = pack_contact(scene.ground, scene.gravity, ps.x.numpy(), ps.vol0.numpy(), cfg.cfl)
        else:
            ground = scene.ground.pack()
        self.contact_height = float(ground.height)  # m, the plane the particle contact pushes from
        raised = raised_modulus(ps.materials, ps.vol0.numpy(), ps.material.numpy(), scene.gravity, g.dx)
        springs = ground_stiffness(scene.ground, ps.materials, raised)
        self.ground_k = wp.array(springs, dtype=wp.vec2, device=dev)
        num_boxes = len(scene.boxes)
        n = ps.n
        shape = wp.vec3i(*g.res)
        split = [0, n] if threads == 1 else [0, n // 2, n]
        self.p2g, self.g2p = [], []
        # Each graph ends with the bounding box of its thread's particles (rows 2 t, 2 t + 1), which
        # the solver's re-fit after a replay reads instead of a pass of its own over all particles.
        self.box = wp.zeros(2 * threads, dtype=wp.vec3, device=dev)
        self._read_box = host_reader(self.box)
        self._box_launches = []
        self._box_stamp = None  # the stamp the sub-steps had after the replay that wrote ``box``
        ensure_loaded(K.p2g, dev)  # p2g and grid_update live in one module
        self._models = [MODELS[m.model].id for m in ps.materials]
        self._g2p_args: list[tuple[int, list]] = []  # per thread: particles, arguments before the cells'
        for t in range(threads):
            p0, count = split[t], split[t + 1] - split[t]
            self._box_launches.append(
                [
                    wp.launch(ops.reset_bounds, 1, [self.box, t], device=dev, record_cmd=True),
                    wp.launch(ops.bounds, count, [ps.x, p0, self.box, t], device=dev, record_cmd=True),
                ]
            )
            self.p2g.append(
                wp.launch(
                    K.p2g,
                    count,
                    [
                        ps.x,
                        ps.v,
                        ps.C,
                        ps.stress,
                        ps.mass,
                        ps.vol0,
                        ps.material,
                        ground,
                        self.ground_k,
                        origin,
                        g.dx,
                        p0,
                        t,
                        shape,
                        a.touched,
                        self.params,
                        a.pending,
                        a.acc[t].flatten(),
                    ],
                    device=dev,
                    record_cmd=True,
                )
            )
            self._g2p_args.append(
                (
                    count,
                    [
                        a.grid_v.flatten(),
                        shape,
                        origin,
                        g.dx,
                        self.params,
                        wp.vec3(*lo),
                        wp.vec3(*hi),
                        a.boxes,
                        num_boxes,
                        cfg.flip,
                        ps.mat_table,
                        ps.material,
                        ps.vol0,
                        ps.mass,
                        p0,
                        t,
                        ps.x,
                        ps.v,
                        ps.C,
                        ps.H,
                        ps.stress,
                        ps.plastic,
                        ps.escaped,
                        a.stats,
                        a.work,
                        ground,
                        self.ground_k,
                        a.pending,
                        a.touched,
                        a.acc[t].flatten(),
                    ],
                )
            )
        # Without the pressure split g2p adds no volume terms; its cell arguments are placeholders.
        cells = wp.zeros((1, 1, 1), dtype=float, device=dev)
        self._record_g2p(False, wp.zeros(1, dtype=float, device=dev), [cells] * threads, [cells] * threads)

        # Coulomb friction on the node layer at the surface (surface_friction), after the whole
        # grid update.
        layer = None if scene.ground is None else scene.ground.surface_friction_layer(g)
        # Two threads update half the active box each (the other waits out a whole update, 4-8 %
        # of a two-thread sub-step otherwise: docs/measurements_sim.md section 22); with the
        # surface friction, which needs the whole grid, the first thread updates it all.
        parts = threads if layer is None else 1
        # On the CPU a thread per slab of blocks across x, on CUDA one per block (K.grid_update).
        slabs = int(self.device.is_cpu)
        blocks = block_res(g.res)
        self.grid_update = [
            wp.launch(
                K.grid_update,
                (blocks[0], 1, 1) if slabs else blocks,
                [
                    a.acc[0],
                    a.acc[1],
                    a.touched,
                    self.params,
                    origin,
                    g.dx,
                    shape,
                    wp.vec3(*scene.gravity),
                    cfg.boundary_cells,
                    ground,
                    a.boxes,
                    num_boxes,
                    part,
                    parts,
                    slabs,
                    a.pending,
                    a.work,
                    a.grid_v,
                ],
                device=dev,
                record_cmd=True,
            )
            for part in range(parts)
        ]
        self.friction = None
        if layer is not None:
            self.friction = wp.launch(
                surface_friction,
                (g.res[0], g.res[1]),
                [a.grid_v, a.touched, self.params, layer, a.work],
                device=dev,
                record_cmd=True,
            )
        # Every row's clock at once (``run``), or each thread its own (``run_graph``).
        self._tick = wp.launch(advance_clock, threads, [self.params, 0], device=dev, record_cmd=True)
        self._ticks = [
            wp.launch(advance_clock, 1, [self.params, t], device=dev, record_cmd=True) for t in range(threads)
        ]
        # Where the two threads' graph replays meet (``run_graph``).
        self._meeting, self._barrier = None, []
        if threads == 2:
            ensure_loaded(barrier, dev)
            self._meeting = new_counter(dev)
            for t in range(2):
                args = [self._meeting, t, LIMIT_CYCLES, YIELD_AFTER_CYCLES]
                self._barrier.append(wp.launch(barrier, 1, args, device=dev, record_cmd=True))

    def _record_g2p(
        self, pressure: bool, cell_lam: wp.array, cell_s: list, cell_k: list, cell_box=None
    ) -> None:
        """(Re-)record the g2p launches: with ``pressure``, the variant that also adds the particles'
        volume terms to the cells (``kernels.g2p_kernel``), each thread to its own arrays."""
        g2p = K.g2p_kernel(self._models, pressure)
        ensure_loaded(g2p, self.device)
        if cell_box is None:
            cell_box = wp.zeros((len(self._g2p_args), 6), dtype=wp.int32, device=self.device)
        self.g2p = [
            wp.launch(
                g2p,
                count,
                args + [cell_lam, cell_s[t], cell_k[t], cell_box],
                device=self.device,
                record_cmd=True,
            )
            for t, (count, args) in enumerate(self._g2p_args)
        ]

    def set_grid_stage(self, fresh: list, post: list, cells: tuple | None = None) -> None:
        """An integrator's recorded launches, one per thread in each list: ``fresh`` after p2g, on
        the thread's particle slice, whenever the particles are scattered afresh (g2p does its work
        otherwise), and ``post`` in every sub-step, in Python and in its graphs, after the whole grid
        update and before g2p, the threads' side by side (they may meet at barriers of their own).
        ``cells`` = (lam per material, per-thread cell sums s, per-thread k, the box rows): g2p adds
        the particles' volume terms to them. The pressure integrator's gather, solve and cells
        (``pressure.py``). Set before the first sub-step: graphs captured earlier would not
        contain them."""
        for name, launches in (("fresh", fresh), ("post-grid", post)):
            if len(launches) not in (0, len(self.g2p)):
                raise ValueError(f"one {name} launch per thread ({len(self.g2p)}), got {len(launches)}")
        if self._graphs:
            raise RuntimeError("set_grid_stage after a graph was captured; set it before stepping")
        self.fresh, self.post_grid = list(fresh), list(post)
        if cells is not None:
            self._record_g2p(True, *cells)

    def invalidate(self) -> None:
        """The particle state was replaced: clear the accumulators, scatter afresh next sub-step."""
        for acc in self.arrays.acc:
            acc.zero_()
        self.arrays.pending.zero_()
        for clear in self.on_invalidate:
            clear()
        self.scattered = False
        self._box_stamp = None

    def replay_bounds(self) -> tuple[list[float], list[float]] | None:
        """The particles' bounding box (min, max corners, m) as the last ``run_graph`` left them;
        None when a sub-step from Python or a new state came after it."""
        if self._box_stamp != self._stamp:
            return None
        rows = self._read_box().tolist()
        return (
            [min(r[a] for r in rows[0::2]) for a in range(3)],
            [max(r[a] for r in rows[1::2]) for a in range(3)],
        )

    @property
    def next_stamp(self) -> int:
        """The number the next sub-step runs with (the stamp its grid_update matches)."""
        return self._stamp

    def set_dt(self, dt: float, damping: float) -> None:
        if dt != self._dt:
            self._field["dt"][:] = dt
            self._field["damping"][:] = math.exp(-damping * dt) if damping > 0.0 else 1.0
            self._dt = dt
            self._dirty = True

    def set_time(self, t: float) -> None:
        """Time at the start of the next sub-step, s (the device moves it on by dt per sub-step)."""
        if t != self._t:
            self._t = t
            self._dirty = True

    def set_active_box(
        self, lo: np.ndarray, hi: np.ndarray, inner_lo: np.ndarray, inner_hi: np.ndarray
    ) -> None:
        """grid_update covers the blocks of nodes lo..hi; g2p flags particles that leave
        [inner_lo, inner_hi] (m) before the next re-fit."""
        f = self._field
        f["block_lo"][:] = lo // K.BLOCK
        f["block_hi"][:] = hi // K.BLOCK
        f["node_lo"][:] = lo
        f["node_hi"][:] = hi
        f["inner_lo"][:] = inner_lo
        f["inner_hi"][:] = inner_hi
        self._dirty = True

    def _sync(self) -> None:
        """Send the host's changes; time and stamp are the device's own (``_advance_host``)."""
        if self._dirty:
            self._field["t"][:] = self._t
            self._field["stamp"][:] = self._stamp
            if self._staging is not self.params:
                wp.copy(self.params, self._staging)
            self._dirty = False

    def _advance_host(self, count: int) -> None:
        """Mirror of ``advance_clock`` (the same float64 sums, so host and device agree exactly)."""
        for _ in range(count):
            self._t += self._dt
        self._stamp += count

    def run(self, worker, between, before=None) -> None:
        """One sub-step: [p2g, fresh,] ``before()`` (periodic folds), grid_update, [post-grid,]
        ``between()`` (grid hooks), g2p (which scatters)."""
        self._sync()
        self._scatter_afresh(worker)
        if before is not None:
            before()
        _launch_halves(self.grid_update, worker)
        if self.friction is not None:
            self.friction.launch()
        if self.post_grid:
            _launch_halves(self.post_grid, worker)
            self._check_meeting()
        between()
        _launch_halves(self.g2p, worker)
        self._tick.launch()
        self._advance_host(1)
        self.scattered = True

    def run_graph(self, count: int, worker=None) -> None:
        """``count`` sub-steps without hooks or walls, replayed from launch graphs captured on first
        use (``wp.capture_begin``: a CUDA graph on a GPU, Warp's C++ replay of the recorded launches
        on the CPU). Same launches, same order, same results as ``run``. With two threads, this
        thread replays the first half's graph and ``worker`` the second's, side by side."""
        if len(self.g2p) == 2 and worker is None:
            raise ValueError("run_graph with two threads needs the worker that replays the second half")
        self._sync()
        self._scatter_afresh(worker)
        # A count is replayed as its binary digits (13 = 8 + 4 + 1), each from a graph of that
        # length: a capture costs about a millisecond per sub-step recorded, so a graph per count
        # (the frame tails take every length below cfl_check_every) would cost more than it saves.
        for piece in (1 << b for b in reversed(range(count.bit_length())) if count >> b & 1):
            graphs = self._graphs.get(piece)
            if graphs is None:
                graphs = self._graphs[piece] = [self._capture(piece, t) for t in range(len(self.g2p))]
            if len(graphs) == 1:
                wp.capture_launch(graphs[0])
                continue
            worker.run(lambda g=graphs: wp.capture_launch(g[1]), lambda g=graphs: wp.capture_launch(g[0]))
            self._check_meeting()
        self.replayed += count
        self._advance_host(count)
        self.scattered = True
        self._box_stamp = self._stamp

    def _scatter_afresh(self, worker) -> None:
        """p2g and the integrator's fresh launches, unless the last g2p scattered these particles."""
        if not self.scattered:
            _launch_halves(self.p2g, worker)
            if self.fresh:
                _launch_halves(self.fresh, worker)

    @property
    def meeting(self) -> wp.array | None:
        """The two threads' barrier state (``spin_barrier``); None with one thread."""
        return self._meeting

    def _check_meeting(self) -> None:
        if self._meeting is not None and abandoned(self._meeting):
            raise RuntimeError(
                "the two MPM threads lost each other (one waited at a barrier past its time limit); "
                "the particle state is half-stepped. Run with solver.threads=1 and report this"
            )

    def _capture(self, count: int, slot: int):
        """The launches of ``count`` sub-steps for thread ``slot``. One thread: grid_update,
        friction, [post-grid,] g2p, clock. Two: each thread updates its part of the grid (the
        first all of it when there is surface friction), and both meet after it, after their
        post-grid launches and after their halves of g2p; each moves its own row of the clock on."""
        pair = len(self.g2p) == 2
        wp.capture_begin(device=self.device)
        try:
            for _ in range(count):
                if slot < len(self.grid_update):
                    self.grid_update[slot].launch()
                if slot == 0 and self.friction is not None:
                    self.friction.launch()
                if pair:
                    self._barrier[slot].launch()
                if self.post_grid:
                    self.post_grid[slot].launch()
                    if pair:
                        self._barrier[slot].launch()
                self.g2p[slot].launch()
                if pair:
                    self._barrier[slot].launch()
                self._ticks[slot].launch()
            for launch in self._box_launches[slot]:
                launch.launch()
        finally:
            graph = wp.capture_end(device=self.device)
        return graph


def _launch_halves(launches: list, worker) -> None:
    """A launch recorded whole, on this thread, or recorded in two halves, on this thread and
    the worker's."""
    if len(launches) == 1:
        launches[0].launch()
    else:
        worker.run(launches[1].launch, launches[0].launch)
