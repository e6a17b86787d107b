"""Warp kernels of the implicit elastic step (``implicit.py``): the energy, its gradient and
Hessian-vector products over the grid velocities, the step's node set-up and the ground's active
set (the Newton-CG vector algebra is ``implicit_algebra``).

The unknown is the grid velocity u (one vec3 per node, dense [nx, ny, nz] arrays; only the
nodes of the step's node list take part). With MLS weights, a particle's velocity gradient is
C_p(u) = (4 / dx^2) sum_i w_ip u_i (x_i - x_p)^T and its deformation gradient after a step of h
seconds F_p(u) = (I + h C_p(u)) F_p^n, as in the explicit g2p. The energy minimised is

    E(u) = sum_i m_i |u_i - u*_i|^2 / 2 + sum_p V0_p psi(F_p(u)),

with the gradient m_i (u_i - u*_i) + h (4 / dx^2) sum_p w_ip V0_p P_p F_p^nT (x_i - x_p). The
models give the Kirchhoff stress tau = P F^T, so P F^nT = tau (I + h C)^-T. The Hessian-vector
product takes the stress derivative dP along dF = h dC F^n by a central difference of the model's
own stress at a fixed strain step ``FD_STRAIN`` (in H = F - I, which keeps small strains exact in
float32): any elastic model of the dispatch works without a hand-written tangent.
"""

from __future__ import annotations

import warp as wp

from physgm.sim.constitutive.common import EYE, MaterialStruct
from physgm.sim.constitutive.dispatch import constitutive_update, energy_density
from physgm.sim.mpm.boundary import GROUND_STICKY, GroundStruct, ground_velocity
from physgm.sim.mpm.grid_layout import load, store
from physgm.sim.mpm.kernels import block_reached, stencil, vec8

wp.set_module_options({"enable_backward": False})

# Strain step of the central difference in the Hessian-vector product. 1e-3 keeps float32
# rounding of H and of the stress (relative 6e-8 of values up to ~0.3) below 1e-4 of the
# difference, and the truncation (relative ~1e-6 for smooth energies) far below CG's tolerance.
FD_STRAIN = wp.constant(1.0e-3)


@wp.func
def velocity_gradient(u: wp.array3d(dtype=wp.vec3), base: wp.vec3i, fx: wp.vec3, w: wp.mat33, inv_dx: float):
    """C = (4 / dx^2) sum_i w_ip u_i (x_i - x_p)^T over the particle's 27 stencil nodes, 1/s."""
    c = wp.mat33(0.0)
    for a in range(3):
        for b in range(3):
            for k in range(3):
                off = wp.vec3(float(a), float(b), float(k)) - fx
                c += (w[a, 0] * w[b, 1] * w[k, 2]) * wp.outer(u[base[0] + a, base[1] + b, base[2] + k], off)
    return (4.0 * inv_dx) * c


@wp.func
def scatter_force(
    out: wp.array3d(dtype=wp.vec3), base: wp.vec3i, fx: wp.vec3, w: wp.mat33, inv_dx: float, s: wp.mat33
):
    """out_i += (4 / dx^2) w_ip s (x_i - x_p) over the 27 stencil nodes."""
    s4 = (4.0 * inv_dx) * s
    for a in range(3):
        for b in range(3):
            for k in range(3):
                off = wp.vec3(float(a), float(b), float(k)) - fx
                wp.atomic_add(
                    out, base[0] + a, base[1] + b, base[2] + k, (w[a, 0] * w[b, 1] * w[k, 2]) * (s4 * off)
                )


@wp.func
def first_piola(H: wp.mat33, mat: MaterialStruct) -> wp.mat33:
    """P = tau F^-T of F = I + H, Pa."""
    H_new, tau, pl = constitutive_update(H, mat, 0.0, 0.0)
    return tau * wp.transpose(wp.inverse(EYE + H))


@wp.kernel
def gradient_pass(
    u: wp.array3d(dtype=wp.vec3),  # [nx, ny, nz] grid velocity iterate, m/s
    x: wp.array(dtype=wp.vec3),  # [P] m, positions at the start of the step
    H: wp.array(dtype=wp.mat33),  # [P] F^n - I
    vol0: wp.array(dtype=float),  # [P] m^3
    materials: wp.array(dtype=MaterialStruct),
    material: wp.array(dtype=int),  # [P]
    origin: wp.vec3,
    dx: float,
    h: float,  # s, step of the energy (theta dt)
    shape: wp.vec3i,
    H_new: wp.array(dtype=wp.mat33),  # [P] out: F_p(u) - I
    grad: wp.array3d(dtype=wp.vec3),  # [nx, ny, nz] out (accumulated): elastic part of dE/du, N s
    energy: wp.array(dtype=wp.float64),  # [1] out (accumulated): sum V0 psi(F(u)), J
):
    p = wp.tid()
    inv_dx = 1.0 / dx
    base, fx, w = stencil((x[p] - origin) * inv_dx, shape)
    C = velocity_gradient(u, base, fx, w, inv_dx)
    Hn = H[p]
    Hu = Hn + h * C * (EYE + Hn)
    H_new[p] = Hu
    mat = materials[material[p]]
    H_out, tau, pl = constitutive_update(Hu, mat, 0.0, 0.0)
    pfn = tau * wp.transpose(wp.inverse(EYE + h * C))  # P F^nT
    scatter_force(grad, base, fx, w, inv_dx, (h * vol0[p]) * pfn)
    wp.atomic_add(energy, 0, wp.float64(vol0[p] * energy_density(Hu, mat)))


@wp.kernel
def hessian_pass(
    d: wp.array3d(dtype=wp.vec3),  # [nx, ny, nz] direction, m/s
    x: wp.array(dtype=wp.vec3),
    H: wp.array(dtype=wp.mat33),  # [P] F^n - I
    H_new: wp.array(dtype=wp.mat33),  # [P] F_p(u) - I at the current iterate
    vol0: wp.array(dtype=float),
    materials: wp.array(dtype=MaterialStruct),
    material: wp.array(dtype=int),
    origin: wp.vec3,
    dx: float,
    h: float,
    shape: wp.vec3i,
    out: wp.array3d(dtype=wp.vec3),  # [nx, ny, nz] out (accumulated): elastic part of (d^2E/du^2) d
):
    p = wp.tid()
    inv_dx = 1.0 / dx
    base, fx, w = stencil((x[p] - origin) * inv_dx, shape)
    Fn = EYE + H[p]
    dF = h * velocity_gradient(d, base, fx, w, inv_dx) * Fn
    size = wp.sqrt(wp.ddot(dF, dF))
    if size == 0.0:
        return
    step = FD_STRAIN / size
    mat = materials[material[p]]
    Hu = H_new[p]
    dP = (first_piola(Hu + step * dF, mat) - first_piola(Hu - step * dF, mat)) * (0.5 / step)
    scatter_force(out, base, fx, w, inv_dx, (h * vol0[p]) * dP * wp.transpose(Fn))


@wp.kernel
def preconditioner_pass(
    x: wp.array(dtype=wp.vec3),
    H: wp.array(dtype=wp.mat33),
    vol0: wp.array(dtype=float),
    materials: wp.array(dtype=MaterialStruct),
    material: wp.array(dtype=int),
    origin: wp.vec3,
    dx: float,
    h: float,
    shape: wp.vec3i,
    diag: wp.array3d(dtype=float),  # [nx, ny, nz] out (accumulated): elastic Hessian diagonal estimate, kg
):
    """Jacobi estimate: the P-wave modulus M = lam + 2 mu in place of the tangent,
    sum_p V0 M h^2 |F^nT grad w_ip|^2."""
    p = wp.tid()
    inv_dx = 1.0 / dx
    base, fx, w = stencil((x[p] - origin) * inv_dx, shape)
    mat = materials[material[p]]
    FnT = wp.transpose(EYE + H[p])
    scale = vol0[p] * (mat.lam + 2.0 * mat.mu) * h * h * 16.0 * inv_dx * inv_dx
    for a in range(3):
        for b in range(3):
            for k in range(3):
                g = (w[a, 0] * w[b, 1] * w[k, 2]) * (FnT * (wp.vec3(float(a), float(b), float(k)) - fx))
                wp.atomic_add(diag, base[0] + a, base[1] + b, base[2] + k, scale * wp.dot(g, g))


@wp.kernel
def collect_nodes(
    grid_v: wp.array4d(dtype=vec8),  # [bx, by, bz, 64] (``grid_layout``) after grid_update
    touched: wp.array3d(dtype=wp.int32),
    stamp: wp.int32,
    lo: wp.vec3i,  # first node of the active box
    nodes: wp.array(dtype=wp.vec3i),  # [G] out: the nodes holding mass this step
    count: wp.array(dtype=int),  # [1] out (accumulated)
):
    i, j, k = wp.tid()
    i += lo[0]
    j += lo[1]
    k += lo[2]
    if not block_reached(touched, i // 4, j // 4, k // 4, stamp):
        return
    if load(grid_v, i, j, k)[3] <= 0.0:
        return
    nodes[wp.atomic_add(count, 0, 1)] = wp.vec3i(i, j, k)


@wp.kernel
def init_nodes(
    nodes: wp.array(dtype=wp.vec3i),
    grid_v: wp.array4d(dtype=vec8),
    shape: wp.vec3i,  # grid node counts
    origin: wp.vec3,
    dx: float,
    h: float,
    gravity: wp.vec3,
    damping: float,  # velocity kept over h
    ground: GroundStruct,
    bound: int,  # separating walls this many nodes inside each grid face
    v_transfer: wp.array3d(dtype=wp.vec3),  # out: APIC transfer velocity
    target: wp.array3d(dtype=wp.vec3),  # out: u* = damping (v_transfer + h g)
    u: wp.array3d(dtype=wp.vec3),  # out: initial iterate (u*, the ground's velocity where it holds)
    free: wp.array3d(dtype=wp.vec3),  # out: 1 per free component, 0 where a boundary fixes it
    mass: wp.array3d(dtype=float),  # out, kg
    diag: wp.array3d(dtype=float),  # out: zeroed for the preconditioner pass
    grad: wp.array3d(dtype=wp.vec3),  # out: zeroed
    region: wp.array3d(dtype=int),  # out: 1 where the ground may hold or release the node (not sticky)
):
    n = nodes[wp.tid()]
    i, j, k = n[0], n[1], n[2]
    g = load(grid_v, i, j, k)
    vt = wp.vec3(g[0] - g[4], g[1] - g[5], g[2] - g[6])
    target_v = damping * (vt + h * gravity)
    pos = origin + wp.vec3(float(i), float(j), float(k)) * dx
    # The ground acts as the explicit grid_update would on the predictor: where it holds a node,
    # the node takes that velocity (normal stopped, Coulomb friction on the tangent) for the step.
    held = ground_velocity(ground, pos, dx, target_v)
    f = wp.vec3(1.0)
    v0 = target_v
    if wp.length_sq(held - target_v) > 0.0:
        f = wp.vec3(0.0)
        v0 = held
    nx = shape[0]
    ny = shape[1]
    nz = shape[2]
    if (i < bound and v0[0] < 0.0) or (i >= nx - bound and v0[0] > 0.0):
        f[0] = 0.0
        v0[0] = 0.0
    if (j < bound and v0[1] < 0.0) or (j >= ny - bound and v0[1] > 0.0):
        f[1] = 0.0
        v0[1] = 0.0
    if (k < bound and v0[2] < 0.0) or (k >= nz - bound and v0[2] > 0.0):
        f[2] = 0.0
        v0[2] = 0.0
    # A downward probe velocity is stopped exactly where the ground holds nodes.
    region[i, j, k] = 0
    if (
        ground.enabled == 1
        and ground.mode != GROUND_STICKY
        and ground_velocity(ground, pos, dx, wp.vec3(0.0, 0.0, -1.0))[2] == 0.0
    ):
        region[i, j, k] = 1
    v_transfer[i, j, k] = vt
    target[i, j, k] = target_v
    u[i, j, k] = v0
    free[i, j, k] = f
    mass[i, j, k] = g[3]
    diag[i, j, k] = 0.0
    grad[i, j, k] = wp.vec3(0.0)


@wp.kernel
def finish_gradient(
    nodes: wp.array(dtype=wp.vec3i),
    u: wp.array3d(dtype=wp.vec3),
    target: wp.array3d(dtype=wp.vec3),
    mass: wp.array3d(dtype=float),
    free: wp.array3d(dtype=wp.vec3),
    grad: wp.array3d(dtype=wp.vec3),  # in: elastic part; out: full gradient on the free components
    sums: wp.array(dtype=wp.float64),  # [3] out (accumulated): kinetic term J, sum |g|^2 / m, sum m
    normal: wp.array3d(dtype=float),  # out: z of the full gradient; < 0 where a held node would lift off
):
    n = nodes[wp.tid()]
    i, j, k = n[0], n[1], n[2]
    m = mass[i, j, k]
    du = u[i, j, k] - target[i, j, k]
    full = grad[i, j, k] + m * du
    normal[i, j, k] = full[2]
    g = wp.cw_mul(free[i, j, k], full)
    grad[i, j, k] = g
    wp.atomic_add(sums, 0, wp.float64(0.5 * m * wp.dot(du, du)))
    wp.atomic_add(sums, 1, wp.float64(wp.dot(g, g) / m))
    wp.atomic_add(sums, 2, wp.float64(m))


@wp.kernel
def finish_hessian(
    nodes: wp.array(dtype=wp.vec3i),
    d: wp.array3d(dtype=wp.vec3),
    mass: wp.array3d(dtype=float),
    free: wp.array3d(dtype=wp.vec3),
    q: wp.array3d(dtype=wp.vec3),  # in: elastic part of H d; out: full H d on the free components
    dq: wp.array(dtype=wp.float64),  # [1] out (accumulated): d . H d
):
    n = nodes[wp.tid()]
    i, j, k = n[0], n[1], n[2]
    v = wp.cw_mul(free[i, j, k], q[i, j, k] + mass[i, j, k] * d[i, j, k])
    q[i, j, k] = v
    wp.atomic_add(dq, 0, wp.float64(wp.dot(d[i, j, k], v)))


@wp.kernel
def write_velocities(
    nodes: wp.array(dtype=wp.vec3i),
    u: wp.array3d(dtype=wp.vec3),
    v_transfer: wp.array3d(dtype=wp.vec3),
    free: wp.array3d(dtype=wp.vec3),
    theta: float,
    grid_v: wp.array4d(dtype=vec8),  # out: (u, mass, v^{n+1} - v_transfer, 0)
):
    """The solve's velocity u moves positions and F over the whole step; the particles' velocity
    change is that of v^{n+1} = v^n + (u - v^n) / theta (the theta method), except on components a
    boundary fixed, which end at u as in the explicit step (no reflection off the ground)."""
    n = nodes[wp.tid()]
    i, j, k = n[0], n[1], n[2]
    un = u[i, j, k]
    du = un - v_transfer[i, j, k]
    f = free[i, j, k]
    s = 1.0 / theta
    dv = wp.vec3(
        du[0] * (1.0 + f[0] * (s - 1.0)), du[1] * (1.0 + f[1] * (s - 1.0)), du[2] * (1.0 + f[2] * (s - 1.0))
    )
    m = load(grid_v, i, j, k)[3]
    store(grid_v, i, j, k, vec8(un[0], un[1], un[2], m, dv[0], dv[1], dv[2], 0.0))


@wp.kernel
def clear_stress_channels(lo: wp.vec3i, acc: wp.array4d(dtype=vec8)):
    """The implicit step takes the stress from its solve: the scatter's explicit stress force
    (accumulator channels 4-6) must not reach grid_update's predictor."""
    i, j, k = wp.tid()
    a = load(acc, i + lo[0], j + lo[1], k + lo[2])
    if a[3] > 0.0:
        a[4] = 0.0
        a[5] = 0.0
        a[6] = 0.0
        store(acc, i + lo[0], j + lo[1], k + lo[2], a)


@wp.kernel
def update_contacts(
    nodes: wp.array(dtype=wp.vec3i),
    region: wp.array3d(dtype=int),
    normal: wp.array3d(dtype=float),
    origin: wp.vec3,
    dx: float,
    ground: GroundStruct,
    u: wp.array3d(dtype=wp.vec3),  # in/out
    free: wp.array3d(dtype=wp.vec3),  # in/out
    changes: wp.array(dtype=int),  # [1] out (accumulated)
):
    """The ground's active set at the solution: a held node whose reaction pulls it down (the
    body would lift it) is released; a free node the solution moves into the ground is held.

    The predictor alone holds the nodes that were moving down, so without this the ground keeps
    the bottom of a rebounding body for a whole step (an adhesion that took 2/3 of a bounce's
    energy at steps of a few ms)."""
    n = nodes[wp.tid()]
    i, j, k = n[0], n[1], n[2]
    if region[i, j, k] == 0:
        return
    if free[i, j, k][2] == 0.0:
        if normal[i, j, k] < 0.0:
            free[i, j, k] = wp.vec3(1.0)
            wp.atomic_add(changes, 0, 1)
    elif u[i, j, k][2] < 0.0:
        pos = origin + wp.vec3(float(i), float(j), float(k)) * dx
        u[i, j, k] = ground_velocity(ground, pos, dx, u[i, j, k])
        free[i, j, k] = wp.vec3(0.0)
        wp.atomic_add(changes, 0, 1)
