"""Weakly compressible inviscid fluid with a J-based pressure.

psi(J) = K/2 (J - 1)^2, so the Kirchhoff stress is tau = K (J - 1) J I (pressure
p = -K (J - 1)), and the deformation gradient is reset to J^(1/3) I every step: a fluid keeps no
memory of shear. J is clamped below at J_MIN_FLUID so a collapsed particle cannot invert.
"""

from __future__ import annotations

import warp as wp

from physgm.sim.constitutive.common import MaterialStruct, det_minus_one, expm1, log1p

J_MIN_FLUID = wp.constant(0.05)


@wp.func
def fluid_update(H: wp.mat33, mat: MaterialStruct, plastic: float, dt: float):
    jm1 = wp.max(det_minus_one(H), J_MIN_FLUID - 1.0)
    J = 1.0 + jm1
    # F = J^(1/3) I, so H = (J^(1/3) - 1) I = expm1(log1p(J - 1) / 3) I, exact for J ~ 1.
    H_new = wp.diag(wp.vec3(expm1(log1p(jm1) / 3.0)))
    return H_new, wp.diag(wp.vec3(mat.bulk * jm1 * J)), plastic


@wp.func
def fluid_energy(H: wp.mat33, mat: MaterialStruct) -> float:
    jm1 = det_minus_one(H)  # J - 1 of F = I + H
    return 0.5 * mat.bulk * jm1 * jm1
