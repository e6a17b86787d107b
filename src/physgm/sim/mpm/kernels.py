"""MLS-MPM transfer kernels (APIC, quadratic B-splines), one code path for CPU and CUDA.

A sub-step is two launches once the first scatter is done (G2P2G, Fei et al. 2021):

    grid_update  accumulators -> velocity: momentum + dt x stress force, gravity, boundary
                 conditions; clears the accumulators
    g2p          grid -> particle velocity and affine matrix C (APIC blended with affine FLIP),
                 F update, return mapping, Kirchhoff stress, advection, domain clamp, statistics,
                 and the particle's scatter for the next sub-step
                 (``g2p_kernel``: one kernel per set of constitutive models, compiled on first use)

The scatter (``scatter_particle``) does not depend on dt: the accumulators hold APIC momentum,
mass and the stress force separately, and grid_update applies dt. So g2p can scatter before the
next step's dt is known, particles are read once per sub-step, and a CPU sub-step needs one
thread hand-off instead of two. ``p2g`` is the same scatter as a kernel of its own, for the
first sub-step and whenever the particle state was replaced (frame retry, new velocities).

Grid nodes are ``vec8``. Accumulators: (APIC momentum xyz, mass, stress force xyz, the ground
contact's resting dashpot c, ``particle_ground``). Velocity grid ``grid_v``: (velocity xyz,
mass, velocity change of this step xyz, the friction impulse a held node leaves for the layer
above, ``boundary.ground_grip``); a hook that overrides a node velocity adds the same change to
components 4-6 (``set_node_velocity``).

The node arrays lie in 4^3-node blocks of 64 consecutive nodes (``grid_layout``), read and
written through ``grid_layout.load`` and ``store``; the stencil sums address the flattened arrays.

Particle kernels take an ``offset`` so the CPU solver can split the particles over threads,
each thread scattering into its own accumulator. The scatter also stamps the 4^3-node block of
the particle's base node with the number of the sub-step it feeds (``touched``); grid_update
visits only the blocks of the active box (the only region particles can reach before the next
re-fit) and skips blocks no stencil reached, so empty space costs a few reads per 64 nodes
instead of 64 node updates (most nodes of a falling object's active box hold no mass); two CPU
threads each update half the active box. dt, time, the stamp
and the active box come from a device array with a row per CPU thread (``substep_params``), so
the same recorded launches serve every sub-step and can be captured as a graph. Particle
stencils are clamped inside the grid, so no index can leave an array whatever the state.
The numpy twin of one sub-step is ``physgm.sim.mpm.reference_mpm`` (tests only).
"""

from __future__ import annotations

import functools
from collections.abc import Iterable

import warp as wp

from physgm.sim.constitutive.common import EYE, MaterialStruct, det_minus_one
from physgm.sim.constitutive.dispatch import update_for
from physgm.sim.linalg import is_finite
from physgm.sim.mpm.boundary import BoxStruct, GroundStruct, box_velocity, ground_grip, ground_velocity
from physgm.sim.mpm.grid_layout import BLOCK, load, stencil_offsets, store
from physgm.sim.mpm.particle_ground import fold_ground_force, particle_ground_force, touches_ground
from physgm.sim.mpm.pressure_kernels import add_cell_terms
from physgm.sim.mpm.stencil_sums import gather_moments, scatter_affine, vec8
from physgm.sim.mpm.substep_params import SubstepParams
from physgm.warp_runtime import FAST_CPU_FLAGS

MODULE_OPTIONS = {"enable_backward": False, "cpu_compiler_flags": FAST_CPU_FLAGS}
wp.set_module_options(MODULE_OPTIONS)

# Columns of the per-sub-step statistics (one row per worker thread).
STAT_VMAX = wp.constant(0)  # max squared particle speed, m^2/s^2
STAT_JMIN = wp.constant(1)  # min det F
STAT_JMAX = wp.constant(2)  # max det F
STAT_BAD = wp.constant(3)  # particles with a non-finite state
STAT_ESCAPED = wp.constant(4)  # particles newly stopped by the domain clamp
STAT_OVERRUN = wp.constant(5)  # particles that left the active grid box (CFL estimate exceeded)
STAT_FLOOR = wp.constant(6)  # particle sub-steps whose elastic trial det F fell below the model's j_floor
NUM_STATS = 7
# Per-thread rows are padded to one 64-byte cache line, so the two CPU threads, which update
# their row for every particle, never write the same line.
STATS_ROW = 16  # floats
WORK_ROW = 8  # float64
# Columns of ``work`` (running sums over the run, restored with the particles on a frame retry).
WORK_DRIVER = wp.constant(0)  # energy put in by the velocity boxes, J
WORK_GROUND = wp.constant(1)  # 1-3: impulse of the ground plane on the nodes, N s
WORK_FACE = wp.constant(4)  # 4-6: impulse of the separating walls at the grid faces, N s
WORK_FACE_CONTACTS = wp.constant(7)  # node updates in which a grid-face wall stopped mass

# A node with less mass than this (kg) is empty. A particle a hair inside the far edge of its
# stencil in all three axes (weights ~0.5 delta^2 each, delta ~ 1e-6 of a cell: a lattice aligned
# with the grid, stretched a little) gives its corner node a float32 denormal mass, ~1e-41 kg, whose
# reciprocal overflows: the node's velocity became inf or NaN and took its particles with it (a
# plasticine stretch diverged in its first frame, docs/measurements_sim.md section 38). The lightest
# particle the planner makes (a 1 mm object of foam) is ~1e-12 kg, so such a node carries less than
# 1e-18 of any particle and its velocity reaches them with a weight as small.
NODE_MASS_FLOOR = wp.constant(1.0e-30)


@wp.func
def stencil(xp: wp.vec3, shape: wp.vec3i):
    """Base node (clamped inside the grid), fractional offset and quadratic weights (rows)."""
    bx = wp.clamp(int(xp[0] - 0.5), 0, shape[0] - 3)
    by = wp.clamp(int(xp[1] - 0.5), 0, shape[1] - 3)
    bz = wp.clamp(int(xp[2] - 0.5), 0, shape[2] - 3)
    fx = xp - wp.vec3(float(bx), float(by), float(bz))
    a = wp.vec3(1.5) - fx
    b = fx - wp.vec3(1.0)
    c = fx - wp.vec3(0.5)
    w0 = 0.5 * wp.cw_mul(a, a)
    w1 = wp.vec3(0.75) - wp.cw_mul(b, b)
    w2 = 0.5 * wp.cw_mul(c, c)
    return wp.vec3i(bx, by, bz), fx, wp.mat33(w0[0], w0[1], w0[2], w1[0], w1[1], w1[2], w2[0], w2[1], w2[2])


@wp.func
def set_node_velocity(grid_v: wp.array4d(dtype=vec8), i: int, j: int, k: int, vel: wp.vec3):
    """Override a node velocity in ``grid_v`` keeping its FLIP increment consistent."""
    g = load(grid_v, i, j, k)
    g[4] = g[4] + vel[0] - g[0]
    g[5] = g[5] + vel[1] - g[1]
    g[6] = g[6] + vel[2] - g[2]
    g[0] = vel[0]
    g[1] = vel[1]
    g[2] = vel[2]
    store(grid_v, i, j, k, g)


@wp.func
def scatter_particle(
    grid: wp.array(dtype=vec8),  # [G] this thread's accumulator, flattened (``grid_layout``)
    xp: wp.vec3,
    vp: wp.vec3,
    cp: wp.mat33,
    stress_p: wp.mat33,  # rest volume x Kirchhoff stress, N m
    m: float,
    origin: wp.vec3,
    dx: float,
    shape: wp.vec3i,
    touched: wp.array3d(dtype=wp.int32),  # [bx, by, bz] sub-step number that last reached each block
    stamp: wp.int32,  # number of the sub-step whose grid_update consumes this scatter
    f_ext: wp.vec3,  # N, external force on the particle (its ground contact, particle_ground)
    c_rest: float,  # N s/m, its contact's resting dashpot (particle_ground)
):
    """Add one particle's APIC momentum, mass, stress force, ``f_ext`` and ``c_rest`` to its 27
    stencil nodes.

    The stencil (base .. base + 2 per axis) lies in the base node's block and the next one along
    each axis, so stamping the base block tells grid_update about all of them.

    MLS-MPM (Hu et al. 2018): node i receives w (m v + m C (x_i - x_p)) and the force
    w (-(4 / dx^2) V0 tau (x_i - x_p)), both affine in the node's offset (i, j, k) in the stencil,
    which is the form ``scatter_affine`` adds.
    """
    inv_dx = 1.0 / dx
    base, fx, w = stencil((xp - origin) * inv_dx, shape)
    bi, bj, bk = base[0] // BLOCK, base[1] // BLOCK, base[2] // BLOCK
    # Written only when it changes: the two threads' particles share the array's few cache lines,
    # and a store from every particle made each thread take the lines from the other.
    if touched[bi, bj, bk] != stamp:
        touched[bi, bj, bk] = stamp
    force = -(4.0 * inv_dx * inv_dx) * stress_p
    affine = m * cp
    q = m * vp - affine * (fx * dx)
    f = f_ext - force * (fx * dx)
    a = affine * dx
    s = force * dx
    ax = wp.vec3(a[0, 0], a[1, 0], a[2, 0])
    ay = wp.vec3(a[0, 1], a[1, 1], a[2, 1])
    az = wp.vec3(a[0, 2], a[1, 2], a[2, 2])
    fx_ = wp.vec3(s[0, 0], s[1, 0], s[2, 0])
    fy_ = wp.vec3(s[0, 1], s[1, 1], s[2, 1])
    fz_ = wp.vec3(s[0, 2], s[1, 2], s[2, 2])
    ox, oy, oz = stencil_offsets(base, shape)
    scatter_affine(
        grid,
        ox,
        oy,
        oz,
        w,
        vec8(q[0], q[1], q[2], m, f[0], f[1], f[2], c_rest),
        vec8(ax[0], ax[1], ax[2], 0.0, fx_[0], fx_[1], fx_[2], 0.0),
        vec8(ay[0], ay[1], ay[2], 0.0, fy_[0], fy_[1], fy_[2], 0.0),
        vec8(az[0], az[1], az[2], 0.0, fz_[0], fz_[1], fz_[2], 0.0),
    )


@wp.kernel
def p2g(
    x: wp.array(dtype=wp.vec3),  # [P] m
    v: wp.array(dtype=wp.vec3),  # [P] m/s
    C: wp.array(dtype=wp.mat33),  # [P] 1/s, APIC affine velocity
    stress: wp.array(dtype=wp.mat33),  # [P] rest volume x Kirchhoff stress, N m
    mass: wp.array(dtype=float),  # [P] kg
    vol0: wp.array(dtype=float),  # [P] rest volume, m^3
    material: wp.array(dtype=int),  # [P] index into ground_k
    ground: GroundStruct,
    ground_k: wp.array(dtype=wp.vec2),  # [M] the particle contact's stiffness (particle_ground)
    origin: wp.vec3,
    dx: float,
    offset: int,
    slot: int,
    shape: wp.vec3i,  # grid node counts
    touched: wp.array3d(dtype=wp.int32),  # [bx, by, bz] out: blocks reached (``scatter_particle``)
    params: wp.array(dtype=SubstepParams),  # [threads] row slot: this sub-step's number
    pending: wp.array2d(dtype=wp.float64),  # [2, 4] out: ground force on the particles, N
    grid: wp.array(dtype=vec8),  # [G] flattened (``grid_layout``): momentum, mass, stress force
):
    p = wp.tid() + offset
    sp = params[slot]
    fg = wp.vec3(0.0)
    cg = float(0.0)  # noqa: UP018 (Warp: set in a branch)
    if touches_ground(ground.particles, ground.height, x[p][2], vol0[p]):
        fg, cg = particle_ground_force(
            ground, ground_k, material[p], x[p], v[p], mass[p], vol0[p], pending, slot
        )
    scatter_particle(grid, x[p], v[p], C[p], stress[p], mass[p], origin, dx, shape, touched, sp.stamp, fg, cg)


@wp.func
def add_impulse(work: wp.array2d(dtype=wp.float64), slot: int, col: int, impulse: wp.vec3):
    """Add an impulse (N s) to columns col .. col + 2 of ``work``."""
    for a in range(3):
        wp.atomic_add(work, slot, col + a, wp.float64(impulse[a]))


@wp.func
def update_node(
    acc0: wp.array4d(dtype=vec8),
    acc1: wp.array4d(dtype=vec8),
    i: int,
    j: int,
    k: int,
    origin: wp.vec3,
    dx: float,
    dt: float,
    t: float,
    gravity: wp.vec3,
    damping: float,
    bound: int,
    shape: wp.vec3i,
    ground: GroundStruct,
    boxes: wp.array(dtype=BoxStruct),
    num_boxes: int,
    slot: int,
    work: wp.array2d(dtype=wp.float64),
    grid_v: wp.array4d(dtype=vec8),
):
    """Accumulators of node (i, j, k) -> its velocity in ``grid_v``; clears the accumulators."""
    g = load(acc0, i, j, k) + load(acc1, i, j, k)
    m = g[3]
    if m <= 0.0:
        store(grid_v, i, j, k, vec8(0.0))
        return
    # Only nodes that received mass were written by the scatter, so only they need clearing.
    store(acc0, i, j, k, vec8(0.0))
    store(acc1, i, j, k, vec8(0.0))
    if m < NODE_MASS_FLOOR:
        store(grid_v, i, j, k, vec8(0.0))
        return
    inv_m = 1.0 / m  # one division instead of four
    v_transfer = inv_m * wp.vec3(g[0], g[1], g[2])  # APIC transfer alone, for the FLIP increment
    vel = damping * (v_transfer + (dt * inv_m) * wp.vec3(g[4], g[5], g[6]) + dt * gravity)
    pos = origin + wp.vec3(float(i), float(j), float(k)) * dx
    if num_boxes > 0:
        v_free = vel
        for b in range(num_boxes):
            vel = box_velocity(boxes[b], pos, t, vel)
        # Mechanical work of the imposed impulse m (v_box - v_free) moving at v_box.
        wp.atomic_add(work, slot, WORK_DRIVER, wp.float64(m * wp.dot(vel - v_free, vel)))
    if g[7] > 0.0 and vel[2] < 0.0 and vel[2] > -ground.rest_speed:
        # The contact's resting dashpot, implicit (particle_ground): slow approaches only.
        vz = vel[2] * m / (m + dt * g[7])
        add_impulse(work, slot, WORK_GROUND, wp.vec3(0.0, 0.0, m * (vz - vel[2])))
        vel[2] = vz
    v_free = vel
    vel = ground_velocity(ground, pos, dx, vel)
    grip = float(0.0)  # noqa: UP018 (Warp: set in a branch); N s left for the surface layer above
    if wp.length_sq(vel - v_free) > 0.0:
        add_impulse(work, slot, WORK_GROUND, m * (vel - v_free))
        grip = ground_grip(ground, m, v_free, vel)
    # Separating walls in the margin keep particles off the grid edge. A scene whose grid holds
    # what it can reach never needs them, so each time they act it is counted (face contacts).
    v_free = vel
    if (i < bound and vel[0] < 0.0) or (i >= shape[0] - bound and vel[0] > 0.0):
        vel[0] = 0.0
    if (j < bound and vel[1] < 0.0) or (j >= shape[1] - bound and vel[1] > 0.0):
        vel[1] = 0.0
    if (k < bound and vel[2] < 0.0) or (k >= shape[2] - bound and vel[2] > 0.0):
        vel[2] = 0.0
    if wp.length_sq(vel - v_free) > 0.0:
        add_impulse(work, slot, WORK_FACE, m * (vel - v_free))
        wp.atomic_add(work, slot, WORK_FACE_CONTACTS, wp.float64(1.0))
    dv = vel - v_transfer
    store(grid_v, i, j, k, vec8(vel[0], vel[1], vel[2], m, dv[0], dv[1], dv[2], grip))


@wp.func
def block_reached(touched: wp.array3d(dtype=wp.int32), bi: int, bj: int, bk: int, stamp: wp.int32) -> bool:
    """Did a stencil reach block (bi, bj, bk)? Stencils start in the block or the one before it."""
    for a in range(2):
        for b in range(2):
            for c in range(2):
                i = bi - a
                j = bj - b
                k = bk - c
                if i >= 0 and j >= 0 and k >= 0:
                    if touched[i, j, k] == stamp:
                        return True
    return False


@wp.kernel
def grid_update(
    acc0: wp.array4d(dtype=vec8),  # [bx, by, bz, 64] (``grid_layout``) first thread's accumulator, cleared
    acc1: wp.array4d(dtype=vec8),  # [bx, by, bz, 64] second thread's accumulator (zeros if unused)
    touched: wp.array3d(dtype=wp.int32),  # [bx, by, bz] blocks reached by this sub-step's scatter
    params: wp.array(dtype=SubstepParams),  # [threads] row slot: dt, time, damping, stamp, active box
    origin: wp.vec3,
    dx: float,
    shape: wp.vec3i,  # grid node counts
    gravity: wp.vec3,
    bound: int,
    ground: GroundStruct,
    boxes: wp.array(dtype=BoxStruct),
    num_boxes: int,
    slot: int,  # this launch's part, its row of params and of work
    parts: int,  # 1, or 2: the two threads each update half the active box's block columns along x
    slabs: int,  # 1: a thread per slab of blocks across x (CPU), 0: a thread per block (below)
    pending: wp.array2d(dtype=wp.float64),  # [2, 4] ground force the scatter gave the particles, N; cleared
    work: wp.array2d(
        dtype=wp.float64
    ),  # [threads, WORK_ROW] running sums: box work, ground and face impulse, face contacts (WORK_*)
    grid_v: wp.array4d(dtype=vec8),  # [bx, by, bz, 64] out: velocity, mass, velocity change
):
    """Updates the blocks of the active box that a stencil reached; blocks outside the box and
    blocks no stencil reached are left as they are (no particle reads them this sub-step), and so
    are the blocks of the other part. Part 0's first thread adds the particles' ground contact to
    the ground impulse (``particle_ground``).

    ``slabs`` 0: one thread per block, launched over the grid's [bx, by, bz] blocks (CUDA). 1: one
    thread per slab of blocks across x, launched over [bx, 1, 1], each looping over the active
    box's blocks of its slab (the CPU, where a thread per block costs time even when it returns
    at once, and a grid sized for a spreading body has tens of thousands of blocks;
    docs/measurements_sim.md section 33). Either way each block's nodes are updated in the same
    order."""
    bi, bj, bk = wp.tid()
    sp = params[slot]
    if bi == 0 and bj == 0 and bk == 0 and slot == 0 and ground.particles != 0:
        fold_ground_force(pending, work, WORK_GROUND, float(sp.dt))
    lo = sp.block_lo
    hi = sp.block_hi
    if bi < lo[0] or bi > hi[0]:
        return
    if (bi - lo[0]) * parts // (hi[0] - lo[0] + 1) != slot:
        return
    j0 = bj
    j1 = bj
    k0 = bk
    k1 = bk
    if slabs != 0:  # the box's blocks of this slab, never past the grid's (the box is clamped to it)
        j0 = wp.max(lo[1], 0)
        j1 = wp.min(hi[1], touched.shape[1] - 1)
        k0 = wp.max(lo[2], 0)
        k1 = wp.min(hi[2], touched.shape[2] - 1)
    elif bj < lo[1] or bk < lo[2] or bj > hi[1] or bk > hi[2]:
        return
    dt = float(sp.dt)
    t = float(sp.t)
    damping = sp.damping
    for cj in range(j0, j1 + 1):
        for ck in range(k0, k1 + 1):
            if block_reached(touched, bi, cj, ck, sp.stamp):
                # The block's nodes in memory order (``grid_layout``).
                for i in range(bi * BLOCK, wp.min((bi + 1) * BLOCK, shape[0])):
                    for j in range(cj * BLOCK, wp.min((cj + 1) * BLOCK, shape[1])):
                        for k in range(ck * BLOCK, wp.min((ck + 1) * BLOCK, shape[2])):
                            update_node(
                                acc0,
                                acc1,
                                i,
                                j,
                                k,
                                origin,
                                dx,
                                dt,
                                t,
                                gravity,
                                damping,
                                bound,
                                shape,
                                ground,
                                boxes,
                                num_boxes,
                                slot,
                                work,
                                grid_v,
                            )


@wp.func
def moment_matrix(bi: vec8, bj: vec8, bk: vec8, c: int) -> wp.mat33:
    """Columns (bi, bj, bk) of node components c, c+1, c+2."""
    return wp.mat33(bi[c], bj[c], bk[c], bi[c + 1], bj[c + 1], bk[c + 1], bi[c + 2], bj[c + 2], bk[c + 2])


def g2p_kernel(models: Iterable[int], pressure: bool = False) -> wp.Kernel:
    """g2p for particles of the given constitutive model ids, compiled on first use.

    With one model the return mapping is that model's alone (``dispatch.UPDATES``), which the
    compiler can inline: a sub-step up to 13 % cheaper than through ``constitutive_update``'s switch
    over every model (docs/measurements_sim.md section 22). Several models take the switch. Each
    variant is a Warp module of its own, so a run compiles only the ones it uses.

    ``pressure``: each particle also adds its volume terms to the cells for the next sub-step's
    pressure solve (``pressure_kernels.add_cell_terms``), from the position and F it has just
    computed, instead of a pass of its own over the particles reading them back.
    """
    return _g2p_kernel(tuple(sorted(set(models))), bool(pressure))


@functools.cache
def _g2p_kernel(models: tuple[int, ...], pressure: bool) -> wp.Kernel:
    update = update_for(models)

    @wp.kernel(module="unique", module_options=MODULE_OPTIONS)
    def g2p(
        grid_v: wp.array(dtype=vec8),  # [G] flattened (``grid_layout``): velocity, mass, velocity change
        shape: wp.vec3i,  # grid node counts
        origin: wp.vec3,
        dx: float,
        params: wp.array(dtype=SubstepParams),  # [threads] row slot: dt, time, inner box, stamp
        clamp_lo: wp.vec3,  # particles are kept inside [clamp_lo, clamp_hi], m
        clamp_hi: wp.vec3,
        boxes: wp.array(dtype=BoxStruct),
        num_boxes: int,
        flip: float,  # affine-FLIP share of the particle (v, C) update; 0 = pure APIC
        materials: wp.array(dtype=MaterialStruct),  # [M]
        material: wp.array(dtype=int),  # [P] index into materials
        vol0: wp.array(dtype=float),  # [P] rest volume, m^3
        mass: wp.array(dtype=float),  # [P] kg
        offset: int,
        slot: int,
        x: wp.array(dtype=wp.vec3),  # [P] in/out
        v: wp.array(dtype=wp.vec3),  # [P] in/out
        C: wp.array(dtype=wp.mat33),  # [P] in/out
        H: wp.array(dtype=wp.mat33),  # [P] in/out, F - I of the elastic deformation gradient F
        stress: wp.array(dtype=wp.mat33),  # [P] out, rest volume x Kirchhoff stress
        plastic: wp.array(dtype=float),  # [P] in/out, plastic history scalar
        escaped: wp.array(dtype=int),  # [P] in/out, 1 once the clamp stopped the particle
        stats: wp.array2d(dtype=float),  # [threads, STATS_ROW] running reductions, first NUM_STATS columns
        work: wp.array2d(
            dtype=wp.float64
        ),  # [threads, WORK_ROW] energy put in by the velocity boxes (column 0), J
        ground: GroundStruct,
        ground_k: wp.array(dtype=wp.vec2),  # [M] the particle contact's stiffness (particle_ground)
        pending: wp.array2d(dtype=wp.float64),  # [2, 4] out: ground force on the particles, N
        touched: wp.array3d(dtype=wp.int32),  # [bx, by, bz] out: blocks reached by the next scatter
        acc: wp.array(dtype=vec8),  # [G] flattened, out: this thread's scatter for the next sub-step
        cell_lam: wp.array(dtype=float),  # [M] the full materials' lam, Pa (``pressure`` only)
        cell_s: wp.array3d(dtype=float),  # out (added to), this thread's volume sums (``pressure`` only)
        cell_k: wp.array3d(dtype=float),
        cell_box: wp.array2d(dtype=wp.int32),  # [threads, 6] out (min / max): the cells reached
    ):
        p = wp.tid() + offset
        sp = params[slot]
        dt = float(sp.dt)
        t = float(sp.t)
        active_lo = sp.inner_lo  # particles must stay inside the active grid box until the next re-fit
        active_hi = sp.inner_hi
        stamp = sp.stamp + 1  # the next sub-step's number
        inv_dx = 1.0 / dx
        xp = x[p]
        base, fx, w = stencil((xp - origin) * inv_dx, shape)
        # Sums of whole nodes with their first moments along each axis (``gather_moments``), so
        # B = sum w v (node - fx)^T needs no per-node outer product; velocity and velocity change
        # come in one pass.
        ox, oy, oz = stencil_offsets(base, shape)
        sums = gather_moments(grid_v, ox, oy, oz, w)
        total = sums[0]
        bi = sums[1]
        bj = sums[2]
        bk = sums[3]
        vel = wp.vec3(total[0], total[1], total[2])
        dvel = wp.vec3(total[4], total[5], total[6])
        c_grid = (4.0 * inv_dx) * (moment_matrix(bi, bj, bk, 0) - wp.outer(vel, fx))
        # Affine FLIP: the particle keeps its own (v, C) plus the grid's change of them this step,
        # blended with the APIC (PIC) values. Pure APIC damps every mode the grid cannot hold on
        # each transfer, so stiff materials (many sub-steps) lose energy quickly; incrementing C
        # along with v keeps angular momentum exact.
        dc = (4.0 * inv_dx) * (moment_matrix(bi, bj, bk, 4) - wp.outer(dvel, fx))
        v_new = vel + flip * (v[p] + dvel - vel)
        c_new = c_grid + flip * (C[p] + dc - c_grid)
        # Particles inside a carrying velocity box move with it: grid conditions alone let the
        # particles at the box edge (whose stencil reaches free nodes) creep out of a clamp.
        v_move = vel
        if num_boxes > 0:
            v_free = v_new
            for b in range(num_boxes):
                if boxes[b].carry != 0:
                    v_new = box_velocity(boxes[b], xp, t, v_new)
                    v_move = box_velocity(boxes[b], xp, t, v_move)
            wp.atomic_add(work, slot, WORK_DRIVER, wp.float64(mass[p] * wp.dot(v_new - v_free, v_new)))
        # The state is H = F - I: stiff materials take steps with strain increments below float32's
        # resolution of numbers near 1, and accumulating F itself would round them away (creep).
        H_trial = H[p] + dt * c_grid * (EYE + H[p])
        mat = materials[material[p]]
        if 1.0 + det_minus_one(H_trial) < mat.j_floor:
            # Checked before the return mapping, which would hide an inversion by clamping it.
            wp.atomic_add(stats, slot, STAT_FLOOR, 1.0)
        H_new, tau, pl = update(H_trial, mat, plastic[p], dt)
        # Positions move with the grid velocity, as in Fei et al. 2021, not with the FLIP share: F
        # follows the grid's velocity gradient, and particles moved by their own noisier velocity
        # slide past each other in ways F never sees. After a hard impact F then describes a crush the
        # positions no longer have, a residual stress that never relaxes (issue 24: a 16-cell jelly hit
        # at twice its wave speed kept 1.2 % of its particles at J < 0.1 and mean J 0.8 after 0.5 s).
        x_new = xp + dt * v_move
        clamped = wp.min(wp.max(x_new, clamp_lo), clamp_hi)
        if clamped[0] != x_new[0] or clamped[1] != x_new[1] or clamped[2] != x_new[2]:
            x_new = clamped
            v_new = wp.vec3(0.0)
            if escaped[p] == 0:
                escaped[p] = 1
                wp.atomic_add(stats, slot, STAT_ESCAPED, 1.0)
        for a in range(3):
            if x_new[a] < active_lo[a] or x_new[a] > active_hi[a]:
                wp.atomic_add(stats, slot, STAT_OVERRUN, 1.0)
                break
        jm1 = det_minus_one(H_new)
        J = 1.0 + jm1
        # One finiteness test: a NaN or inf anywhere in the new state propagates into this sum.
        check = wp.dot(x_new + v_new, wp.vec3(1.0)) + J + wp.ddot(tau, wp.mat33(1.0))
        if not is_finite(check):
            # Keep the state usable for indexing; the solver rejects the frame (and re-scatters).
            wp.atomic_add(stats, slot, STAT_BAD, 1.0)
            x_new = xp
            v_new = wp.vec3(0.0)
        else:
            wp.atomic_max(stats, slot, STAT_VMAX, wp.dot(v_new, v_new))  # squared; the solver takes the root
            wp.atomic_min(stats, slot, STAT_JMIN, J)
            wp.atomic_max(stats, slot, STAT_JMAX, J)
            fg = wp.vec3(0.0)
            cg = float(0.0)  # noqa: UP018 (Warp: set in a branch)
            if touches_ground(ground.particles, ground.height, x_new[2], vol0[p]):
                fg, cg = particle_ground_force(
                    ground, ground_k, material[p], x_new, v_new, mass[p], vol0[p], pending, slot
                )
            tau_v = vol0[p] * tau
            scatter_particle(
                acc, x_new, v_new, c_new, tau_v, mass[p], origin, dx, shape, touched, stamp, fg, cg
            )
            if wp.static(pressure):  # compiled in only for the pressure split
                lam = cell_lam[material[p]]
                add_cell_terms(
                    x_new, jm1, vol0[p], mat.model, lam, origin, dx, slot, cell_s, cell_k, cell_box
                )
        x[p] = x_new
        v[p] = v_new
        C[p] = c_new
        H[p] = H_new
        stress[p] = vol0[p] * tau
        plastic[p] = pl

    return g2p
