"""Weakly compressible inviscid fluid with a J-based pressure.

Pressure linear in density, p = K (1/J - 1) = K (rho / rho0 - 1) (the weakly compressible SPH
equation of state): psi(J) = K (J - 1 - log J), Kirchhoff stress tau = J sigma = K (J - 1) I, and
a sound speed sqrt(K / rho0) at every compression, so the CFL step stays right. The deformation
gradient is reset to J^(1/3) I every step: a fluid keeps no memory of shear. J is clamped below at
J_MIN_FLUID so a collapsed particle cannot invert.

Before issue 24 the pressure was p = K (1 - J) (psi = K/2 (J - 1)^2, tau = K (J - 1) J): its
Kirchhoff stress, which is what pushes on the grid, peaks at K / 4 at J = 1/2 and falls to 0 as
J -> 0, so a particle compressed below J = 1/2 softened, collapsed to the clamp and stayed there
(the sweep's fluid at E = 1e5 Pa, nu = 0.01 dropped at 0.86 times its sound speed kept one).
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
