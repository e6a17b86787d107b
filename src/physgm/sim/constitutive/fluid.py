"""Weakly compressible inviscid fluid with a J-based pressure.

Pressure linear in density, p = K (1/J - 1) = K (rho / rho0 - 1) (the weakly compressible SPH
equation of state): psi(J) = K (J - 1 - log J), Kirchhoff stress tau = J sigma = K (J - 1) I, and
a sound speed sqrt(K / rho0) at every compression, so the CFL step stays right. The deformation
gradient is reset to J^(1/3) I every step: a fluid keeps no memory of shear. J is clamped below at
J_MIN_FLUID so a collapsed particle cannot invert.

Not psi = K/2 (J - 1)^2: its Kirchhoff stress, which pushes on the grid, falls to 0 below J = 1/2, so
compressed particles collapsed onto the clamp (docs/measurements_sim.md, section 9).
"""

from __future__ import annotations

import warp as wp

from physgm.sim.constitutive.common import MaterialStruct, det_minus_one, expm1, log1p

J_MIN_FLUID = wp.constant(0.05)


@wp.func
def fluid_update(H: wp.mat33, mat: MaterialStruct, plastic: float, dt: float):
    jm1 = wp.max(det_minus_one(H), J_MIN_FLUID - 1.0)
    # F = J^(1/3) I, so H = (J^(1/3) - 1) I = expm1(log1p(J - 1) / 3) I, exact for J ~ 1.
    H_new = wp.diag(wp.vec3(expm1(log1p(jm1) / 3.0)))
    return H_new, wp.diag(wp.vec3(mat.bulk * jm1)), plastic


@wp.func
def fluid_energy(H: wp.mat33, mat: MaterialStruct) -> float:
    x = wp.max(det_minus_one(H), J_MIN_FLUID - 1.0)  # J - 1 of F = I + H, at most down to the clamp
    if wp.abs(x) < 1.0e-2:
        # x - log(1 + x) by its series: a stiff fluid strains ~1e-6, where the difference of the
        # two float32 terms would keep no digit of their x^2 / 2.
        return mat.bulk * x * x * (0.5 - x * (1.0 / 3.0 - x * (0.25 - 0.2 * x)))
    return mat.bulk * (x - wp.log(1.0 + x))
