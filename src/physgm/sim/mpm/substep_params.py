"""The values that change between sub-steps, held on the device for the sub-step kernels.

dt, time, damping, the sub-step's number (the scatter's block stamp) and the active grid box
live in a small array that the kernels read, not in launch arguments: one row per CPU thread,
each read and moved on only by its own thread, so two threads that replay graphs never race on
the clock (the host writes every row alike). So a sequence of
recorded launches means the same thing every time it runs: ``advance_clock`` moves time and
the stamp on at the end of each sub-step, and the host writes the array (through numpy views of
its fields) only when dt or the active box change, every ``cfl_check_every`` sub-steps at most.
That is what lets the solver capture the sub-step once as a launch graph (``wp.capture_begin``:
a CUDA graph, or Warp's C++ replay of recorded CPU launches) and replay it without returning to
Python (``launches.py``).
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.struct
class SubstepParams:
    dt: wp.float64  # s, this sub-step's step (float64 so time adds up exactly as on the host)
    t: wp.float64  # s, time at the start of this sub-step
    damping: float  # velocity kept per step, exp(-k dt) of the scene's drag rate k; 1 = none
    stamp: wp.int32  # this sub-step's number (kernels.scatter_particle stamps blocks with it)
    block_lo: wp.vec3i  # first and last 4^3-node block grid_update covers (the active box)
    block_hi: wp.vec3i
    node_lo: wp.vec3i  # first and last node of the active box (the surface-friction columns)
    node_hi: wp.vec3i
    inner_lo: wp.vec3  # m: g2p flags particles that leave [inner_lo, inner_hi] before the re-fit
    inner_hi: wp.vec3


@wp.kernel
def advance_clock(params: wp.array(dtype=SubstepParams), first: int):
    """End of a sub-step: row ``first`` + tid's time moves on by dt and its next sub-step gets the
    next number."""
    row = first + wp.tid()
    p = params[row]
    p.t = p.t + p.dt
    p.stamp = p.stamp + 1
    params[row] = p
