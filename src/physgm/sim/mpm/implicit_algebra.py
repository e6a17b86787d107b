"""Vector algebra of the implicit step's Newton-CG over its node list (``nodes``: the grid nodes
holding mass this sub-step; vectors are dense [nx, ny, nz] vec3 arrays read only there)."""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def zero_nodes(nodes: wp.array(dtype=wp.vec3i), a: wp.array3d(dtype=wp.vec3)):
    n = nodes[wp.tid()]
    a[n[0], n[1], n[2]] = wp.vec3(0.0)


@wp.kernel
def cg_start(
    nodes: wp.array(dtype=wp.vec3i),
    grad: wp.array3d(dtype=wp.vec3),
    mass: wp.array3d(dtype=float),
    diag: wp.array3d(dtype=float),
    r: wp.array3d(dtype=wp.vec3),  # out: -grad
    z: wp.array3d(dtype=wp.vec3),  # out: preconditioned r
    p: wp.array3d(dtype=wp.vec3),  # out: = z
    d: wp.array3d(dtype=wp.vec3),  # out: solution, 0
    rz: wp.array(dtype=wp.float64),  # [1] out (accumulated): r . z
):
    n = nodes[wp.tid()]
    i, j, k = n[0], n[1], n[2]
    rr = -grad[i, j, k]
    zz = rr / (mass[i, j, k] + diag[i, j, k])
    r[i, j, k] = rr
    z[i, j, k] = zz
    p[i, j, k] = zz
    d[i, j, k] = wp.vec3(0.0)
    wp.atomic_add(rz, 0, wp.float64(wp.dot(rr, zz)))


@wp.kernel
def cg_update(
    nodes: wp.array(dtype=wp.vec3i),
    alpha: float,
    p: wp.array3d(dtype=wp.vec3),
    q: wp.array3d(dtype=wp.vec3),
    mass: wp.array3d(dtype=float),
    diag: wp.array3d(dtype=float),
    d: wp.array3d(dtype=wp.vec3),  # in/out: d += alpha p
    r: wp.array3d(dtype=wp.vec3),  # in/out: r -= alpha q
    z: wp.array3d(dtype=wp.vec3),  # out: preconditioned r
    sums: wp.array(dtype=wp.float64),  # [2] out (accumulated): r . z, r . r / m
):
    n = nodes[wp.tid()]
    i, j, k = n[0], n[1], n[2]
    d[i, j, k] = d[i, j, k] + alpha * p[i, j, k]
    rr = r[i, j, k] - alpha * q[i, j, k]
    m = mass[i, j, k]
    zz = rr / (m + diag[i, j, k])
    r[i, j, k] = rr
    z[i, j, k] = zz
    wp.atomic_add(sums, 0, wp.float64(wp.dot(rr, zz)))
    wp.atomic_add(sums, 1, wp.float64(wp.dot(rr, rr) / m))


@wp.kernel
def cg_direction(
    nodes: wp.array(dtype=wp.vec3i), beta: float, z: wp.array3d(dtype=wp.vec3), p: wp.array3d(dtype=wp.vec3)
):
    n = nodes[wp.tid()]
    i, j, k = n[0], n[1], n[2]
    p[i, j, k] = z[i, j, k] + beta * p[i, j, k]


@wp.kernel
def axpy_nodes(
    nodes: wp.array(dtype=wp.vec3i),
    alpha: float,
    d: wp.array3d(dtype=wp.vec3),
    u0: wp.array3d(dtype=wp.vec3),
    u: wp.array3d(dtype=wp.vec3),  # out: u0 + alpha d
):
    n = nodes[wp.tid()]
    i, j, k = n[0], n[1], n[2]
    u[i, j, k] = u0[i, j, k] + alpha * d[i, j, k]


@wp.kernel
def dot_nodes(
    nodes: wp.array(dtype=wp.vec3i),
    a: wp.array3d(dtype=wp.vec3),
    b: wp.array3d(dtype=wp.vec3),
    out: wp.array(dtype=wp.float64),  # [1] out (accumulated)
):
    n = nodes[wp.tid()]
    wp.atomic_add(out, 0, wp.float64(wp.dot(a[n[0], n[1], n[2]], b[n[0], n[1], n[2]])))
