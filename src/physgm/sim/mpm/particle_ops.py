"""Particle-wise helper kernels: initial stress, energies, bounds, sorting, pointwise stress.

The numpy twins of the constitutive functions these call are in ``constitutive.reference``. The
module compiles with the CPU flags of ``kernels`` (``FAST_CPU_FLAGS``), so the constitutive models
run here as they run in the sub-step, and the tests that hold these kernels to the twins hold the
solver's compiled models.
"""

from __future__ import annotations

import warp as wp

from physgm.sim.constitutive.common import MaterialStruct
from physgm.sim.constitutive.dispatch import constitutive_update, energy_density
from physgm.warp_runtime import FAST_CPU_FLAGS

wp.set_module_options({"enable_backward": False, "cpu_compiler_flags": FAST_CPU_FLAGS})


@wp.kernel
def init_stress(
    H: wp.array(dtype=wp.mat33),  # [P] in/out F - I (projected onto the yield surface)
    materials: wp.array(dtype=MaterialStruct),
    material: wp.array(dtype=int),
    vol0: wp.array(dtype=float),
    plastic: wp.array(dtype=float),
    stress: wp.array(dtype=wp.mat33),  # [P] out
):
    p = wp.tid()
    H_new, tau, pl = constitutive_update(H[p], materials[material[p]], plastic[p], 0.0)
    H[p] = H_new
    stress[p] = vol0[p] * tau
    plastic[p] = pl


@wp.kernel
def particle_energy(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    H: wp.array(dtype=wp.mat33),  # F - I
    materials: wp.array(dtype=MaterialStruct),
    material: wp.array(dtype=int),
    mass: wp.array(dtype=float),
    vol0: wp.array(dtype=float),
    gravity: wp.vec3,
    affine_inertia: float,  # D = dx^2 / 4 of the quadratic B-spline
    out: wp.array(dtype=wp.float64),  # [3] kinetic, gravitational, elastic, J
):
    p = wp.tid()
    m = mass[p]
    c = C[p]
    kinetic = 0.5 * m * (wp.dot(v[p], v[p]) + affine_inertia * wp.ddot(c, c))
    wp.atomic_add(out, 0, wp.float64(kinetic))
    wp.atomic_add(out, 1, wp.float64(-m * wp.dot(gravity, x[p])))
    wp.atomic_add(out, 2, wp.float64(vol0[p] * energy_density(H[p], materials[material[p]])))


@wp.kernel
def cell_keys(
    x: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    dx: float,
    shape: wp.vec3i,
    keys: wp.array(dtype=int),  # [2P] (radix sort scratch), first P written
    values: wp.array(dtype=int),  # [2P], first P set to the identity permutation
):
    p = wp.tid()
    c = (x[p] - origin) / dx
    i = wp.clamp(int(c[0]), 0, shape[0] - 1)
    j = wp.clamp(int(c[1]), 0, shape[1] - 1)
    k = wp.clamp(int(c[2]), 0, shape[2] - 1)
    keys[p] = (i * shape[1] + j) * shape[2] + k
    values[p] = p


@wp.kernel
def gather_vec3(src: wp.array(dtype=wp.vec3), perm: wp.array(dtype=int), dst: wp.array(dtype=wp.vec3)):
    p = wp.tid()
    dst[p] = src[perm[p]]


@wp.kernel
def gather_mat33(src: wp.array(dtype=wp.mat33), perm: wp.array(dtype=int), dst: wp.array(dtype=wp.mat33)):
    p = wp.tid()
    dst[p] = src[perm[p]]


@wp.kernel
def gather_float(src: wp.array(dtype=float), perm: wp.array(dtype=int), dst: wp.array(dtype=float)):
    p = wp.tid()
    dst[p] = src[perm[p]]


@wp.kernel
def gather_int(src: wp.array(dtype=int), perm: wp.array(dtype=int), dst: wp.array(dtype=int)):
    p = wp.tid()
    dst[p] = src[perm[p]]


@wp.kernel
def evaluate_constitutive(
    F_in: wp.array(dtype=wp.mat33),  # [N] trial deformation gradients
    plastic_in: wp.array(dtype=float),  # [N]
    materials: wp.array(dtype=MaterialStruct),
    material: wp.array(dtype=int),  # [N]
    dt: float,
    F_out: wp.array(dtype=wp.mat33),  # [N] after the return mapping
    tau_out: wp.array(dtype=wp.mat33),  # [N] Kirchhoff stress, Pa
    plastic_out: wp.array(dtype=float),  # [N]
    energy_out: wp.array(dtype=float),  # [N] energy density of F_in, J/m^3
):
    """Pointwise constitutive update, for tests and for callers that need stresses."""
    n = wp.tid()
    mat = materials[material[n]]
    H = F_in[n] - wp.identity(n=3, dtype=float)
    H_new, tau, pl = constitutive_update(H, mat, plastic_in[n], dt)
    F_out[n] = wp.identity(n=3, dtype=float) + H_new
    tau_out[n] = tau
    plastic_out[n] = pl
    energy_out[n] = energy_density(H, mat)


@wp.kernel
def reset_bounds(out: wp.array(dtype=wp.vec3), row: int):  # [2 rows] out: +inf, -inf, for ``bounds``
    out[2 * row] = wp.vec3(wp.inf)
    out[2 * row + 1] = wp.vec3(-wp.inf)


@wp.kernel
def bounds(
    x: wp.array(dtype=wp.vec3),  # [P] m
    first: int,  # the launch covers particles first, first + 1, ...
    out: wp.array(dtype=wp.vec3),  # [2 rows] in/out: row's running min and max (preset by ``reset_bounds``)
    row: int,
):
    """Bounding box of a range of particles (atomic min / max)."""
    p = first + wp.tid()
    wp.atomic_min(out, 2 * row, x[p])
    wp.atomic_max(out, 2 * row + 1, x[p])
