"""Fixed-corotated elasticity (Stomakhin et al. 2012), no plasticity.

psi = mu sum_i (sigma_i - 1)^2 + lam/2 (J - 1)^2 with rotation-variant stretches sigma_i, so it is
defined and smooth for inverted F. Kirchhoff stress tau = 2 mu (F - R) F^T + lam (J - 1) J I,
and R F^T = U diag(sigma) U^T is the rotation-variant left stretch. For J > 0 that stretch is
sqrt(F F^T), taken in closed form in terms of b - I (``linalg.left_stretch_minus_identity``); inverted or
degenerate F use the rotation-variant SVD.
"""

from __future__ import annotations

import warp as wp

from physgm.sim.constitutive.common import EYE, MaterialStruct, det_minus_one, green_minus_identity
from physgm.sim.linalg import left_stretch_minus_identity, rv_svd


@wp.func
def fixed_corotated_update(H: wp.mat33, mat: MaterialStruct, plastic: float, dt: float):
    jm1 = det_minus_one(H)
    J = 1.0 + jm1
    vol = wp.diag(wp.vec3(mat.lam * jm1 * J))
    if J > 0.0:
        # b - V = (b - I) - (V - I): both small, so the stress keeps full float32 precision.
        D = green_minus_identity(H)
        Vm = left_stretch_minus_identity(D, jm1)
        if wp.isfinite(Vm[0, 0]):
            return H, 2.0 * mat.mu * (D - Vm) + vol, plastic
    U, sigma, Vr = rv_svd(EYE + H)
    tau = U * wp.diag(2.0 * mat.mu * wp.cw_mul(sigma, sigma - wp.vec3(1.0))) * wp.transpose(U)
    return H, tau + vol, plastic


@wp.func
def fixed_corotated_energy(H: wp.mat33, mat: MaterialStruct) -> float:
    U, sigma, V = rv_svd(EYE + H)
    jm1 = det_minus_one(H)
    d = sigma - wp.vec3(1.0)
    return mat.mu * wp.dot(d, d) + 0.5 * mat.lam * jm1 * jm1
