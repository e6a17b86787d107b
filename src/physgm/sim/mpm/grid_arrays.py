"""The grid-side Warp arrays of one solver: accumulators, node velocities, block stamps, reductions."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from physgm.sim.mpm import kernels as K
from physgm.sim.mpm.boundary import BoxStruct, VelocityBox
from physgm.sim.mpm.grid_layout import block_res, node_shape


def lazy_zeros(shape: tuple[int, ...], dtype, device) -> wp.array:
    """``wp.zeros`` of a float32 vector type, on the CPU backed by numpy's zeroed allocation,
    whose pages the system maps on first touch. A solver on a grid wide enough for what a body may
    reach (a landing spreading sand two metres, ``mpm_run.followed_grid``) then allocates its node
    arrays without writing zeros over every page, and pays only for the pages its particles reach
    (docs/measurements_sim.md section 33)."""
    device = wp.get_device(device)
    if not device.is_cpu:
        return wp.zeros(shape, dtype=dtype, device=device)
    if dtype._wp_scalar_type_ is not wp.float32:
        raise TypeError(f"lazy_zeros takes vectors of float32, got {dtype}")
    zeros = np.zeros((*shape, *dtype._shape_), dtype=np.float32)
    return wp.array(zeros, dtype=dtype, device=device, copy=False)  # keeps a reference to ``zeros``


@dataclass(frozen=True)
class GridArrays:
    """The grid-side arrays the sub-step kernels read and write, allocated once per solver.

    ``SubstepLaunches`` allocates and owns them; the side walls and grid hooks change ``grid_v``
    (and the walls the accumulators) in place.
    """

    # The node arrays lie in blocks (``grid_layout``): [bx, by, bz, 64] for a grid of [nx, ny, nz].
    acc: tuple[wp.array, wp.array]  # 2 x [bx, by, bz, 64] vec8, one scatter accumulator per thread
    grid_v: wp.array  # [bx, by, bz, 64] vec8: velocity m/s, mass kg, velocity change (see kernels)
    touched: wp.array  # [bx, by, bz] int32 stamps of the blocks a scatter reached (kernels.scatter_particle)
    stats: wp.array  # [2, STATS_ROW] per-thread running reductions of g2p (kernels.STAT_*)
    work: wp.array  # [2, WORK_ROW] float64 per-thread driver work, J, and impulses (kernels.WORK_*)
    pending: wp.array  # [2, 4] float64 per-thread ground force the last scatter gave, N (particle_ground)
    boxes: wp.array  # [max(B, 1)] BoxStruct, the scene's velocity boxes

    @classmethod
    def allocate(cls, res: tuple[int, int, int], boxes: Sequence[VelocityBox], device) -> GridArrays:
        return cls(
            acc=tuple(lazy_zeros(node_shape(res), K.vec8, device) for _ in range(2)),
            grid_v=lazy_zeros(node_shape(res), K.vec8, device),
            touched=wp.zeros(block_res(res), dtype=wp.int32, device=device),
            stats=wp.zeros((2, K.STATS_ROW), dtype=float, device=device),
            work=wp.zeros((2, K.WORK_ROW), dtype=wp.float64, device=device),
            pending=wp.zeros((2, 4), dtype=wp.float64, device=device),
            boxes=wp.array([b.pack() for b in boxes] or [BoxStruct()], dtype=BoxStruct, device=device),
        )
