"""Coulomb friction of the ground on the node layer at its surface, after the grid update.

With contact at the surface (``GroundPlane.held_depth`` > 0, ``boundary``) the held nodes lie 7/8
cell below the plane and reach the lowest particles only through the tails of their stencils
(weight ~0.1), while the node layer just above the held one, 1/8 cell above the plane, carries
most of their mass (weight ~0.75). The normal condition stays on the held layer, so contact
still begins at the surface; on a Coulomb ground the layer above also loses sliding momentum,
column by column, up to mu x (the normal impulse of the held node below it, less the friction
that node used itself; ``boundary.ground_grip``). Its normal velocity is left alone, so lift-off
stays free, and a column acts only while its held node pushes, i.e. while the body's lowest
particles are within 5/8 cell of the plane and pressing on it.
"""

from __future__ import annotations

import warp as wp

from physgm.sim.mpm.grid_layout import load
from physgm.sim.mpm.kernels import BLOCK, WORK_GROUND, add_impulse, block_reached, set_node_velocity, vec8
from physgm.sim.mpm.substep_params import SubstepParams


@wp.kernel
def surface_friction(
    grid_v: wp.array4d(dtype=vec8),  # [bx, by, bz, 64] in/out (``grid_layout``): velocity, mass, dv, grip
    touched: wp.array3d(dtype=wp.int32),  # [bx, by, bz] blocks reached by this sub-step's scatter
    params: wp.array(dtype=SubstepParams),  # [threads] row 0: this sub-step's number, the active box
    layer: int,  # k of the top held node layer; the surface layer is layer + 1
    work: wp.array2d(dtype=wp.float64),  # [threads, WORK_ROW] running sums; the ground impulse is added
):
    i, j = wp.tid()  # one thread per grid column; columns outside the active box return at once
    sp = params[0]
    if i < sp.node_lo[0] or j < sp.node_lo[1] or i > sp.node_hi[0] or j > sp.node_hi[1]:
        return
    stamp = sp.stamp
    k = layer + 1
    # Nodes of blocks no stencil reached hold a stale state (kernels.grid_update).
    if not block_reached(touched, i // BLOCK, j // BLOCK, k // BLOCK, stamp):
        return
    if not block_reached(touched, i // BLOCK, j // BLOCK, layer // BLOCK, stamp):
        return
    held = load(grid_v, i, j, layer)
    node = load(grid_v, i, j, k)
    m = node[3]
    grip = held[7]
    if m <= 0.0 or held[3] <= 0.0 or grip <= 0.0:
        return
    v = wp.vec3(node[0], node[1], node[2])
    sliding = m * wp.length(wp.vec3(v[0], v[1], 0.0))  # tangential momentum, N s
    if sliding <= 0.0:
        return
    keep = float(0.0)  # noqa: UP018 (Warp: a dynamic variable, set in a branch)
    if sliding > grip:
        keep = 1.0 - grip / sliding
    vel = wp.vec3(keep * v[0], keep * v[1], v[2])
    add_impulse(work, 0, WORK_GROUND, m * (vel - v))
    set_node_velocity(grid_v, i, j, k, vel)
