"""Warp kernels of the implicit pressure step (``pressure.py``): the cells' volume terms and the
conjugate-gradient solve on the grid.

Cells are indexed by their lowest corner node (i, j, k), so cell arrays share the node arrays'
[nx, ny, nz] shape (the last layer along each axis is never a cell). The divergence of a node
velocity field u at the centre of cell c is the trilinear (Q1) element's,

    (D u)_c = sum over the 8 corners n of g_n . u_n,   g_n = (2a - 1, 2b - 1, 2c - 1) / (4 dx)

for the corner at offset (a, b, c) in {0, 1}^3; its transpose takes a cell scalar t_c to the
node vectors sum_c t_c g_n. The solve runs over the box of cells the particles reached this
sub-step (``gather_cells`` widens it); the cell sums are zero outside it between sub-steps.
"""

from __future__ import annotations

import warp as wp

from physgm.sim.constitutive.common import FIXED_COROTATED, NEO_HOOKEAN, MaterialStruct, det_minus_one, log1p
from physgm.sim.constitutive.fixed_corotated import J_B
from physgm.sim.constitutive.fixed_corotated import J_FLOOR as FC_J_FLOOR
from physgm.sim.constitutive.neo_hookean import J_E, J_FLOOR, log_ext, log_ext_derivative
from physgm.sim.mpm.grid_layout import load, store
from physgm.sim.mpm.spin_barrier import wait_for_partner
from physgm.sim.mpm.stencil_sums import vec8
from physgm.sim.mpm.substep_params import SubstepParams

wp.set_module_options({"enable_backward": False})

BOX_EMPTY = wp.constant(1 << 30)  # an empty box: lo at +BOX_EMPTY, hi at -BOX_EMPTY


@wp.func
def volume_terms(model: int, jm1: float, lam: float) -> wp.vec2:
    """The lam part of a model's volume energy phi(J): (J phi'(J), J^2 phi''(J)) in Pa.

    J phi' is the Kirchhoff pressure the model's lam terms give (its volume barrier's lam share
    included, so that with the explicit step's lam = 0 copy the two parts add up to the model);
    J^2 phi'' its stiffness against a relative volume change, clamped at 0 (neo-Hookean's turns
    negative above J = e, where the model softens)."""
    J = 1.0 + jm1
    tau = float(0.0)  # noqa: UP018 (Warp: set in a branch)
    k = float(0.0)  # noqa: UP018
    if model == NEO_HOOKEAN:
        if J >= J_E:
            g = log1p(jm1)
            tau = lam * g
            k = lam * (1.0 - g)
        else:  # the log extension and the lam share of the barrier (neo_hookean.py)
            g = log_ext(J)
            gp = log_ext_derivative(J)
            L = wp.log(wp.max(J, J_FLOOR) / J_E)
            tau = lam * g * gp * J - 0.5 * lam * L * L
            k = lam * (gp * gp * J * J - L + 0.5 * L * L)
    elif model == FIXED_COROTATED:
        if J >= J_B:
            tau = lam * jm1 * J
            k = lam * J * J
        else:  # the barrier with the lam share of its modulus (fixed_corotated.py)
            L = wp.log(wp.max(J, FC_J_FLOOR) / J_B)
            tau = -0.25 * lam - 0.5 * lam * L * L
            k = -lam * L - tau
    return wp.vec2(tau, wp.max(k, 0.0))


@wp.func
def add_cell_terms(
    xp: wp.vec3,  # m
    jm1: float,  # J - 1
    vol0: float,  # m^3
    model: int,
    lam: float,  # Pa, the full material's
    origin: wp.vec3,
    dx: float,
    slot: int,
    cell_s: wp.array3d(dtype=float),
    cell_k: wp.array3d(dtype=float),
    box: wp.array2d(dtype=wp.int32),
):
    """One particle's volume terms to the 8 cells whose centres surround it, with trilinear
    weights w, so the sums change smoothly as particles move between cells (with each particle in
    its own cell alone, a particle crossing a face moved its whole pressure to the next cell, and
    a 16-cell rubber drop blew up: docs/measurements_sim.md section 29), and the cells to the box
    of this thread's row."""
    rel = (xp - origin) / dx - wp.vec3(0.5)
    i0 = int(wp.floor(rel[0]))
    j0 = int(wp.floor(rel[1]))
    k0 = int(wp.floor(rel[2]))
    f = rel - wp.vec3(float(i0), float(j0), float(k0))
    terms = vol0 * volume_terms(model, jm1, lam)
    for a in range(2):
        wa = wp.where(a == 0, 1.0 - f[0], f[0])
        for b in range(2):
            wb = wa * wp.where(b == 0, 1.0 - f[1], f[1])
            for e in range(2):
                w = wb * wp.where(e == 0, 1.0 - f[2], f[2])
                wp.atomic_add(cell_s, i0 + a, j0 + b, k0 + e, w * terms[0])
                wp.atomic_add(cell_k, i0 + a, j0 + b, k0 + e, w * terms[1])
    wp.atomic_min(box, slot, 0, i0)
    wp.atomic_min(box, slot, 1, j0)
    wp.atomic_min(box, slot, 2, k0)
    wp.atomic_max(box, slot, 3, i0 + 1)
    wp.atomic_max(box, slot, 4, j0 + 1)
    wp.atomic_max(box, slot, 5, k0 + 1)


@wp.kernel
def gather_cells(
    x: wp.array(dtype=wp.vec3),  # [P] m
    H: wp.array(dtype=wp.mat33),  # [P] F - I
    vol0: wp.array(dtype=float),  # [P] m^3
    materials: wp.array(dtype=MaterialStruct),  # [M] the full materials: the grid takes their lam
    material: wp.array(dtype=int),  # [P]
    origin: wp.vec3,
    dx: float,
    offset: int,  # first particle of this thread's slice
    slot: int,  # this thread's row of ``box``
    cell_s: wp.array3d(dtype=float),  # out (accumulated), this thread's: sum w V0 J phi', N m
    cell_k: wp.array3d(dtype=float),  # out (accumulated), this thread's: sum w V0 J^2 phi'', N m
    box: wp.array2d(dtype=wp.int32),  # [threads, 6] out (min / max): the cells reached, lo xyz, hi xyz
):
    """Each particle's volume terms to its cells (``add_cell_terms``), for a particle state the
    last g2p did not produce (the first sub-step, a retried frame); g2p adds them otherwise. Each
    CPU thread sums its particles into arrays of its own; the solve adds them."""
    p = wp.tid() + offset
    mat = materials[material[p]]
    add_cell_terms(
        x[p], det_minus_one(H[p]), vol0[p], mat.model, mat.lam, origin, dx, slot, cell_s, cell_k, box
    )


@wp.func
def corner_gradient(a: int, b: int, e: int, inv4dx: float) -> wp.vec3:
    return wp.vec3(float(2 * a - 1), float(2 * b - 1), float(2 * e - 1)) * inv4dx


@wp.func
def cell_divergence(u: wp.array3d(dtype=wp.vec3), c: wp.vec3i, inv4dx: float) -> float:
    div = float(0.0)  # noqa: UP018 (Warp: a variable, summed in the loop)
    for a in range(2):
        for b in range(2):
            for e in range(2):
                div += wp.dot(corner_gradient(a, b, e, inv4dx), u[c[0] + a, c[1] + b, c[2] + e])
    return div


@wp.func
def node_transpose(t: wp.array3d(dtype=float), n: wp.vec3i, inv4dx: float) -> wp.vec3:
    """sum over the (up to) 8 cells around node n of t_c g_n(c)."""
    out = wp.vec3(0.0)
    for a in range(2):
        for b in range(2):
            for e in range(2):
                i = n[0] - a
                j = n[1] - b
                k = n[2] - e
                if i >= 0 and j >= 0 and k >= 0:
                    out += t[i, j, k] * corner_gradient(a, b, e, inv4dx)
    return out


@wp.func
def node_sum(a: wp.array3d(dtype=float), i: int, j: int, k: int) -> float:
    """Sum of a cell array over the (up to) 8 cells around node (i, j, k)."""
    s = float(0.0)  # noqa: UP018 (Warp: a variable, summed in the loop)
    for da in range(2):
        for db in range(2):
            for de in range(2):
                if i - da >= 0 and j - db >= 0 and k - de >= 0:
                    s += a[i - da, j - db, k - de]
    return s


@wp.func
def meet(counter: wp.array(dtype=wp.int64), slot: int, threads: int, limits: wp.vec2l):
    """Both CPU threads' halves of the solve wait here for each other (one thread: no wait);
    ``limits``: the barrier's limit and yield cycles (``spin_barrier``)."""
    if threads == 2:
        wait_for_partner(counter, slot, limits[0], limits[1])


@wp.func
def total(partial: wp.array2d(dtype=wp.float64), col: int, threads: int) -> wp.float64:
    """The threads' partial sums of column ``col``, added in one fixed order on every thread, so both
    take the same decisions from them."""
    out = partial[0, col]
    if threads == 2:
        out = out + partial[1, col]
    return out


@wp.kernel
def solve(
    slot: int,  # this thread's half of the box (0 with one thread)
    threads: int,  # 1 or 2 CPU threads sharing the solve, meeting at ``counter``
    counter: wp.array(dtype=wp.int64),  # the two halves' barrier state (``spin_barrier``)
    limits: wp.vec2l,  # the barrier's limit and yield cycles
    grid_v: wp.array4d(dtype=vec8),  # in/out: the grid update's velocities, corrected (``grid_layout``)
    cell_s: wp.array3d(dtype=float),  # in/out: the first thread's sums, the total in the solve, then 0
    cell_k: wp.array3d(dtype=float),
    cell_s1: wp.array3d(dtype=float),  # in/out: the second thread's sums (unread with one), then 0
    cell_k1: wp.array3d(dtype=float),
    box: wp.array2d(dtype=wp.int32),  # [threads, 6] in/out: the cells reached, reset for the next sub-step
    params: wp.array(dtype=SubstepParams),  # [threads] row 0: this sub-step's dt
    tolerance: float,  # m/s, rms velocity residual at which the solve stops
    max_iterations: int,
    theta: float,  # in [0.5, 1]: the volume term at J + theta h D v (``pressure.py``)
    partial: wp.array2d(dtype=wp.float64),  # [2, 4] scratch: each thread's partial sums
    t: wp.array3d(dtype=float),  # scratch, cell scalars
    mass: wp.array3d(dtype=float),  # scratch, node masses (0: not in the solve)
    diag: wp.array3d(dtype=float),  # scratch, theta h^2 (D^T K D)_nn
    d: wp.array3d(dtype=wp.vec3),  # in/out: the velocity correction, kept for the next warm start
    r: wp.array3d(dtype=wp.vec3),  # scratch, residual
    z: wp.array3d(dtype=wp.vec3),  # scratch, preconditioned residual
    p: wp.array3d(dtype=wp.vec3),  # scratch, search direction
    q: wp.array3d(dtype=wp.vec3),  # scratch, the operator times p
    w: wp.array3d(dtype=wp.vec3),  # scratch, the operator times z
    d_stamp: wp.array3d(dtype=wp.int32),  # in/out: the solve that last wrote a node's d
    d_old: wp.array3d(dtype=wp.vec3),  # in/out: the final d of the solve before the last
    old_stamp: wp.array3d(dtype=wp.int32),  # in/out: the solve whose final d is in d_old (-1: none)
    stats: wp.array(dtype=wp.float64),  # [3] in/out: solves, iterations, unconverged (``PressureCounters``)
    dx: float,
):
    """One sub-step's solve (``pressure.py``), launched with dim 1 once per CPU thread: each takes
    the cell and node layers of its half of the box along x and the two meet between passes (a
    pass reads its neighbours' layer). On the CPU, where Warp runs a launch's threads one after
    the other anyway, this is the work of a launch per pass without the launches, and the launch
    is recorded, so the sub-step's graphs replay it. (On a GPU it is correct but serial.)"""
    h = float(params[0].dt)
    inv4dx = 0.25 / dx
    h2 = theta * h * h  # the operator is M + theta h^2 D^T K D
    scale = h2 * inv4dx * inv4dx
    last = box.shape[0] - 1
    ci0 = wp.min(box[0, 0], box[last, 0])
    cj0 = wp.min(box[0, 1], box[last, 1])
    ck0 = wp.min(box[0, 2], box[last, 2])
    ci1 = wp.max(box[0, 3], box[last, 3])
    cj1 = wp.max(box[0, 4], box[last, 4])
    ck1 = wp.max(box[0, 5], box[last, 5])
    solves = int(stats[0]) + 1
    # This thread's layers: cells [c_lo, c_hi) and nodes [n_lo, n_hi) along x.
    mid = (ci0 + ci1 + 1) // 2
    c_lo = ci0
    c_hi = ci1 + 1
    n_lo = ci0
    n_hi = ci1 + 2
    if threads == 2:
        if slot == 0:
            c_hi = mid
            n_hi = mid
        else:
            c_lo = mid
            n_lo = mid
    if ci0 <= ci1:
        if threads == 2:  # the second thread's sums into the first's arrays
            for i in range(c_lo, c_hi):
                for j in range(cj0, cj1 + 1):
                    for k in range(ck0, ck1 + 1):
                        cell_s[i, j, k] = cell_s[i, j, k] + cell_s1[i, j, k]
                        cell_k[i, j, k] = cell_k[i, j, k] + cell_k1[i, j, k]
                        cell_s1[i, j, k] = 0.0
                        cell_k1[i, j, k] = 0.0
            meet(counter, slot, threads, limits)
        # Nodes: mass, Jacobi diagonal, warm start, and theta (v* + d0) in p for the start's divergence.
        # The warm start extrapolates the last two solves' corrections linearly where a node had
        # both (the last one alone where it had one): on the 50-frame rubber drop's first 21 frames
        # that took 5.1 iterations a solve instead of 8.1 (docs/measurements_sim.md section 30).
        mass_sum = wp.float64(0.0)
        for i in range(n_lo, n_hi):
            for j in range(cj0, cj1 + 2):
                for k in range(ck0, ck1 + 2):
                    g = load(grid_v, i, j, k)
                    m = g[3]
                    mass[i, j, k] = m
                    if m > 0.0:
                        mass_sum += wp.float64(m)
                        diag[i, j, k] = scale * node_sum(cell_k, i, j, k)
                        d0 = wp.vec3(0.0)
                        if d_stamp[i, j, k] == solves - 1:
                            prev_d = d[i, j, k]
                            d0 = prev_d
                            if old_stamp[i, j, k] == solves - 2:
                                d0 = 2.0 * prev_d - d_old[i, j, k]
                            d_old[i, j, k] = prev_d
                            old_stamp[i, j, k] = solves - 1
                        d[i, j, k] = d0
                        p[i, j, k] = theta * (wp.vec3(g[0], g[1], g[2]) + d0)
                    else:
                        p[i, j, k] = wp.vec3(0.0)
        partial[slot, 0] = mass_sum
        meet(counter, slot, threads, limits)
        for i in range(c_lo, c_hi):
            for j in range(cj0, cj1 + 1):
                for k in range(ck0, ck1 + 1):
                    c = wp.vec3i(i, j, k)
                    t[i, j, k] = cell_s[i, j, k] + h * cell_k[i, j, k] * cell_divergence(p, c, inv4dx)
        meet(counter, slot, threads, limits)
        rz = wp.float64(0.0)
        rr = wp.float64(0.0)
        for i in range(n_lo, n_hi):
            for j in range(cj0, cj1 + 2):
                for k in range(ck0, ck1 + 2):
                    m = mass[i, j, k]
                    if m > 0.0:
                        rv = -h * node_transpose(t, wp.vec3i(i, j, k), inv4dx) - m * d[i, j, k]
                        zv = rv / (m + diag[i, j, k])
                        r[i, j, k] = rv
                        z[i, j, k] = zv
                        rz += wp.float64(wp.dot(rv, zv))
                        rr += wp.float64(wp.dot(rv, rv) / m)
                    else:  # the cells' divergence reads z on every corner
                        z[i, j, k] = wp.vec3(0.0)
        partial[slot, 1] = rz
        partial[slot, 2] = rr
        meet(counter, slot, threads, limits)  # every node has read t and z is whole
        mass_total = total(partial, 0, threads)
        rz = total(partial, 1, threads)
        res = wp.sqrt(float(total(partial, 2, threads) / mass_total))
        # Conjugate gradients in Chronopoulos and Gear's form: the operator is applied to the
        # preconditioned residual z (w = A z) and the search direction's product follows by the
        # recurrence q = A p = w + beta q, so both of an iteration's sums are taken after its one
        # product and it makes three passes (cells, nodes, nodes) instead of four; the iterates are
        # plain preconditioned CG's.
        rz_old = wp.float64(0.0)
        alpha = wp.float64(0.0)
        its = int(0)  # noqa: UP018 (Warp: a variable, counted in the loop)
        while res > tolerance and its < max_iterations and rz > wp.float64(0.0):
            for i in range(c_lo, c_hi):
                for j in range(cj0, cj1 + 1):
                    for k in range(ck0, ck1 + 1):
                        t[i, j, k] = cell_k[i, j, k] * cell_divergence(z, wp.vec3i(i, j, k), inv4dx)
            meet(counter, slot, threads, limits)
            zw = wp.float64(0.0)
            for i in range(n_lo, n_hi):
                for j in range(cj0, cj1 + 2):
                    for k in range(ck0, ck1 + 2):
                        m = mass[i, j, k]
                        if m > 0.0:
                            zz = z[i, j, k]
                            ww = m * zz + h2 * node_transpose(t, wp.vec3i(i, j, k), inv4dx)
                            w[i, j, k] = ww
                            zw += wp.float64(wp.dot(zz, ww))
            partial[slot, 3] = zw
            meet(counter, slot, threads, limits)  # every node has read t; the sums are whole
            beta = wp.float64(0.0)
            if its > 0:
                beta = rz / rz_old
                alpha = rz / (total(partial, 3, threads) - beta * rz / alpha)
            else:
                alpha = rz / total(partial, 3, threads)
            step = float(alpha)
            blend = float(beta)
            rz_new = wp.float64(0.0)
            rr = wp.float64(0.0)
            for i in range(n_lo, n_hi):
                for j in range(cj0, cj1 + 2):
                    for k in range(ck0, ck1 + 2):
                        m = mass[i, j, k]
                        if m > 0.0:
                            pp = z[i, j, k]
                            qq = w[i, j, k]
                            if its > 0:  # the first direction is z itself (p and q are stale)
                                pp = pp + blend * p[i, j, k]
                                qq = qq + blend * q[i, j, k]
                            p[i, j, k] = pp
                            q[i, j, k] = qq
                            d[i, j, k] = d[i, j, k] + step * pp
                            rv = r[i, j, k] - step * qq
                            zv = rv / (m + diag[i, j, k])
                            r[i, j, k] = rv
                            z[i, j, k] = zv
                            rz_new += wp.float64(wp.dot(rv, zv))
                            rr += wp.float64(wp.dot(rv, rv) / m)
            partial[slot, 1] = rz_new
            partial[slot, 2] = rr
            meet(counter, slot, threads, limits)  # z is whole; the sums were read before anyone rewrites them
            rz_old = rz
            rz = total(partial, 1, threads)
            res = wp.sqrt(float(total(partial, 2, threads) / mass_total))
            its += 1
        # The corrected velocities; the cell sums back to 0 for the next sub-step's gather.
        for i in range(n_lo, n_hi):
            for j in range(cj0, cj1 + 2):
                for k in range(ck0, ck1 + 2):
                    if mass[i, j, k] > 0.0:
                        d_stamp[i, j, k] = solves
                        g = load(grid_v, i, j, k)
                        dd = d[i, j, k]
                        for e in range(3):
                            g[e] = g[e] + dd[e]
                            g[4 + e] = g[4 + e] + dd[e]
                        store(grid_v, i, j, k, g)
        for i in range(c_lo, c_hi):
            for j in range(cj0, cj1 + 1):
                for k in range(ck0, ck1 + 1):
                    cell_s[i, j, k] = 0.0
                    cell_k[i, j, k] = 0.0
                    t[i, j, k] = 0.0
        if slot == 0:
            stats[1] = stats[1] + wp.float64(its)
            if res > tolerance:
                stats[2] = stats[2] + wp.float64(1.0)
    meet(counter, slot, threads, limits)  # both have read the box and stats[0]
    if slot == 0:
        stats[0] = wp.float64(solves)
        for row in range(box.shape[0]):
            for a in range(3):
                box[row, a] = BOX_EMPTY
                box[row, 3 + a] = -BOX_EMPTY
