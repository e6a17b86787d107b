"""The recorded kernel launches of one MPM sub-step, per worker thread.

Recording once (``wp.launch(..., record_cmd=True)``) and replaying keeps the Python cost of a
sub-step to a few microseconds; only dt, time, the active grid box and damping are re-set.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from physgm.sim import kernels as K
from physgm.sim.boundary import no_ground
from physgm.warp_runtime import ensure_loaded


class SubstepLaunches:
    """p2g, grid_update and g2p launches for ``threads`` particle slices of ``solver``."""

    def __init__(self, solver) -> None:
        self.solver = solver
        self._record()
        self._dt = None
        self.timed = bool(len(solver.scene.boxes))  # only the velocity boxes depend on time

    def _record(self) -> None:
        s = self.solver
        g, dev, cfg, ps = s.grid, s.device, s.config, s.particles
        origin = wp.vec3(*g.origin)
        lo, hi = g.interior(1)
        ground = s.scene.ground.pack() if s.scene.ground is not None else no_ground()
        num_boxes = len(s.scene.boxes)
        n = s.num_particles
        shape = wp.vec3i(*g.res)
        split = [0, n] if s.threads == 1 else [0, n // 2, n]
        self.p2g, self.grid_update, self.g2p = [], [], []
        ensure_loaded(K.p2g, dev)  # all three kernels live in one module
        for t in range(s.threads):
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
                        0.0,
                        p0,
                        shape,
                        s.acc[t].flatten(),
                    ],
                    device=dev,
                    record_cmd=True,
                )
            )
            self.grid_update.append(
                wp.launch(
                    K.grid_update,
                    g.res,
                    [
                        s.acc[0],
                        s.acc[1],
                        wp.vec3i(0, 0, 0),
                        origin,
                        g.dx,
                        0.0,
                        0.0,
                        wp.vec3(*s.scene.gravity),
                        1.0,
                        cfg.boundary_cells,
                        ground,
                        s.boxes,
                        num_boxes,
                        t,
                        s.work,
                        s.grid_v,
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
                        s.grid_v.flatten(),
                        shape,
                        origin,
                        g.dx,
                        0.0,
                        wp.vec3(*lo),
                        wp.vec3(*hi),
                        wp.vec3(*lo),
                        wp.vec3(*hi),
                        0.0,
                        s.boxes,
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
                        s.stats,
                        s.work,
                    ],
                    device=dev,
                    record_cmd=True,
                )
            )

    @property
    def all(self) -> tuple:
        return (*self.p2g, *self.grid_update, *self.g2p)

    def set_dt(self, dt: float, damping: float) -> None:
        if dt != self._dt:
            for launch in self.all:
                launch.set_param_by_name("dt", dt)
            if damping > 0.0:
                for launch in self.grid_update:
                    launch.set_param_by_name("damping", math.exp(-damping * dt))
            self._dt = dt

    def set_time(self, t: float) -> None:
        for launch in (*self.grid_update, *self.g2p):
            launch.set_param_by_name("t", t)

    def set_active_box(
        self, lo: np.ndarray, hi: np.ndarray, inner_lo: np.ndarray, inner_hi: np.ndarray
    ) -> None:
        """grid_update covers nodes lo..hi (split along x over the threads); g2p flags particles
        that leave [inner_lo, inner_hi] (m) before the next re-fit."""
        threads = len(self.grid_update)
        cut = [lo[0], (lo[0] + hi[0] + 1) // 2, hi[0] + 1] if threads == 2 else [lo[0], hi[0] + 1]
        for t, launch in enumerate(self.grid_update):
            launch.set_dim((max(cut[t + 1] - cut[t], 0), hi[1] - lo[1] + 1, hi[2] - lo[2] + 1))
            launch.set_param_by_name("lo", wp.vec3i(int(cut[t]), int(lo[1]), int(lo[2])))
        for launch in self.g2p:
            launch.set_param_by_name("active_lo", wp.vec3(*inner_lo))
            launch.set_param_by_name("active_hi", wp.vec3(*inner_hi))

    def run(self, worker, between) -> None:
        """One sub-step: p2g, grid_update, ``between()`` (grid hooks), g2p."""
        if worker is None:
            self.p2g[0].launch()
            self.grid_update[0].launch()
            between()
            self.g2p[0].launch()
        else:
            worker.run(self.p2g[1].launch, self.p2g[0].launch)
            worker.run(self.grid_update[1].launch, self.grid_update[0].launch)
            between()
            worker.run(self.g2p[1].launch, self.g2p[0].launch)
