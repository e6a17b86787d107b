"""The recorded kernel launches of one MPM sub-step, per worker thread; they own the grid arrays.

In steady state a sub-step is grid_update then g2p, which also scatters the particles for the
next sub-step (``kernels``); p2g runs only when the accumulators were invalidated.

Recording once (``wp.launch(..., record_cmd=True)``) and replaying keeps the Python cost of a
sub-step to a few microseconds; only dt, time, the active grid box and damping are re-set.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from physgm.sim.mpm import kernels as K
from physgm.sim.mpm.boundary import no_ground
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.grid_arrays import GridArrays
from physgm.sim.mpm.particle_store import ParticleStore
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.stepping import SolverConfig
from physgm.sim.mpm.surface_friction import surface_friction
from physgm.warp_runtime import ensure_loaded


class SubstepLaunches:
    """p2g and g2p launches for ``threads`` particle slices, and one grid_update.

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
        self._record(particles, grid, scene, config, threads, device)
        self._dt = None
        self.scattered = False  # the accumulators hold the current particles' scatter
        # Number of the last sub-step run; the scatter stamps the blocks it reaches with the number
        # of the sub-step that consumes it, so stale stamps never match and nothing needs clearing.
        self.stamp = 0
        self.timed = bool(len(scene.boxes))  # only the velocity boxes depend on time

    def _record(
        self, ps: ParticleStore, g: GridSpec, scene: Scene, cfg: SolverConfig, threads: int, dev
    ) -> None:
        a = self.arrays
        origin = wp.vec3(*g.origin)
        lo, hi = g.interior(1)
        ground = scene.ground.pack() if scene.ground is not None else no_ground()
        num_boxes = len(scene.boxes)
        n = ps.n
        shape = wp.vec3i(*g.res)
        split = [0, n] if threads == 1 else [0, n // 2, n]
        self.p2g, self.g2p = [], []
        ensure_loaded(K.p2g, dev)  # all three kernels live in one module
        for t in range(threads):
            p0, count = split[t], split[t + 1] - split[t]
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
                        origin,
                        g.dx,
                        p0,
                        shape,
                        a.touched,
                        0,
                        a.acc[t].flatten(),
                    ],
                    device=dev,
                    record_cmd=True,
                )
            )
            self.g2p.append(
                wp.launch(
                    K.g2p,
                    count,
                    [
                        a.grid_v.flatten(),
                        shape,
                        origin,
                        g.dx,
                        0.0,
                        wp.vec3(*lo),
                        wp.vec3(*hi),
                        wp.vec3(*lo),
                        wp.vec3(*hi),
                        0.0,
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
                        a.touched,
                        0,
                        a.acc[t].flatten(),
                    ],
                    device=dev,
                    record_cmd=True,
                )
            )

        # With the empty blocks skipped, grid_update is a few percent of a sub-step: one launch on
        # the calling thread costs less than another thread hand-off.
        self.grid_update = wp.launch(
            K.grid_update,
            K.block_res(g.res),
            [
                a.acc[0],
                a.acc[1],
                a.touched,
                0,
                wp.vec3i(0, 0, 0),
                origin,
                g.dx,
                0.0,
                0.0,
                wp.vec3(*scene.gravity),
                1.0,
                cfg.boundary_cells,
                ground,
                a.boxes,
                num_boxes,
                0,
                a.work,
                a.grid_v,
            ],
            device=dev,
            record_cmd=True,
        )
        # Coulomb friction on the node layer at the surface (surface_friction).
        self.friction = None
        layer = None if scene.ground is None else scene.ground.surface_friction_layer(g)
        if layer is not None:
            self.friction = wp.launch(
                surface_friction,
                (g.res[0], g.res[1]),
                [a.grid_v, a.touched, 0, wp.vec2i(0, 0), layer, a.work],
                device=dev,
                record_cmd=True,
            )

    def invalidate(self) -> None:
        """The particle state was replaced: clear the accumulators, scatter afresh next sub-step."""
        for acc in self.arrays.acc:
            acc.zero_()
        self.scattered = False

    def set_dt(self, dt: float, damping: float) -> None:
        if dt != self._dt:
            for launch in (self.grid_update, *self.g2p):
                launch.set_param_by_name("dt", dt)
            if damping > 0.0:
                self.grid_update.set_param_by_name("damping", math.exp(-damping * dt))
            self._dt = dt

    def set_time(self, t: float) -> None:
        for launch in (self.grid_update, *self.g2p):
            launch.set_param_by_name("t", t)

    def set_active_box(
        self, lo: np.ndarray, hi: np.ndarray, inner_lo: np.ndarray, inner_hi: np.ndarray
    ) -> None:
        """grid_update covers the blocks of nodes lo..hi; g2p flags particles that leave
        [inner_lo, inner_hi] (m) before the next re-fit."""
        blo = [int(v) // K.BLOCK for v in lo]
        bhi = [int(v) // K.BLOCK for v in hi]
        self.grid_update.set_dim(tuple(h - l + 1 for l, h in zip(blo, bhi, strict=True)))
        self.grid_update.set_param_by_name("lo", wp.vec3i(*blo))
        if self.friction is not None:
            self.friction.set_dim((int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1))
            self.friction.set_param_by_name("lo", wp.vec2i(int(lo[0]), int(lo[1])))
        for launch in self.g2p:
            launch.set_param_by_name("active_lo", wp.vec3(*inner_lo))
            launch.set_param_by_name("active_hi", wp.vec3(*inner_hi))

    def _set_stamp(self) -> None:
        self.stamp += 1
        if not self.scattered:
            for launch in self.p2g:
                launch.set_param_by_name("stamp", self.stamp)
        self.grid_update.set_param_by_name("stamp", self.stamp)
        if self.friction is not None:
            self.friction.set_param_by_name("stamp", self.stamp)
        for launch in self.g2p:
            launch.set_param_by_name("stamp", self.stamp + 1)

    def run(self, worker, between, before=None) -> None:
        """One sub-step: [p2g,] ``before()`` (periodic folds), grid_update, ``between()`` (grid
        hooks), g2p (which scatters)."""
        self._set_stamp()
        if not self.scattered:
            _launch_halves(self.p2g, worker)
        if before is not None:
            before()
        self.grid_update.launch()
        if self.friction is not None:
            self.friction.launch()
        between()
        _launch_halves(self.g2p, worker)
        self.scattered = True


def _launch_halves(launches: list, worker) -> None:
    """The whole launch on this thread (``launches[0]`` without a worker), or its two halves on
    this thread and the worker's."""
    if worker is None:
        launches[0].launch()
    else:
        worker.run(launches[1].launch, launches[0].launch)
