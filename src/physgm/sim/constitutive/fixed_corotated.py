"""Fixed-corotated elasticity (Stomakhin et al. 2012) with a volume barrier, no plasticity.

psi = mu sum_i (sigma_i - 1)^2 + psi_vol(J) with rotation-variant stretches sigma_i. Kirchhoff
stress tau = 2 mu (F - R) F^T + p(J) I with p = J psi_vol'(J), and R F^T = U diag(sigma) U^T is
the rotation-variant left stretch. For J > 0 that stretch is sqrt(F F^T), taken in closed form in
terms of b - I (``linalg.left_stretch_minus_identity``); degenerate F use the rotation-variant SVD.

Volume term. Stomakhin's psi_vol = lam/2 (J - 1)^2 gives p = lam (J - 1) J, which is smallest at
J = 1/2 and returns to 0 at J = 0: a particle crushed flat holds no pressure, so nothing pushes
it back, and an impact faster than the wave speed leaves a tenth of a jelly cube at J ~ 0 for
good (issue 24). Below J_B = 1/2 we continue p with p(J) = -lam/4 - (k/2) log(J / J_B)^2: equal
value and slope at J_B (C^1) for any k, and p -> -inf as J -> 0, so psi_vol grows without bound (a
barrier) and a crushed particle pushes back. k = lam + 2 mu, the P-wave modulus, not lam: lam
vanishes as nu -> 0 (and the shear term 2 mu (sigma - 1) sigma returns to 0 at sigma = 0), so with
k = lam a nu = 0.01 cube hit at twice its wave speed was crushed below J = 1e-4. The tangent in the
current configuration, J p'(J) = -k log(J / J_B), grows only logarithmically, so the explicit step
needs no smaller dt until J ~ 1e-2 (k |log(0.02)| ~ 3 k). Above J_B the model is Stomakhin's
exactly. J <= 0 cannot be reached from J > 0 through the barrier in exact arithmetic; a step that
overshoots below the model's floor is rejected by the divergence guard (``MODELS[...].j_floor``),
and J is clamped to J_FLOOR for the pressure so the rejected state stays finite.
"""

from __future__ import annotations

import warp as wp

from physgm.sim.constitutive.common import EYE, MaterialStruct, det_minus_one, green_minus_identity
from physgm.sim.linalg import is_finite, left_stretch_minus_identity, rv_svd

J_B = wp.constant(0.5)  # below this volume ratio the barrier continues the volume term
J_FLOOR = wp.constant(1.0e-6)  # volume ratio the pressure is clamped to for J <= 0


@wp.func
def volume_pressure(jm1: float, lam: float, k: float) -> float:
    """Volumetric Kirchhoff pressure p(J) = J psi_vol'(J), Pa (module docstring), from J - 1;
    ``k`` is the barrier modulus lam + 2 mu."""
    J = 1.0 + jm1
    if J >= J_B:
        return lam * jm1 * J
    L = wp.log(wp.max(J, J_FLOOR) / J_B)
    return -0.25 * lam - 0.5 * k * L * L


@wp.func
def volume_energy(jm1: float, lam: float, k: float) -> float:
    """psi_vol(J), J/m^3: lam/2 (J - 1)^2 above J_B, the barrier's integral below it."""
    J = 1.0 + jm1
    if J >= J_B:
        return 0.5 * lam * jm1 * jm1
    L = wp.log(wp.max(J, J_FLOOR) / J_B)
    return 0.125 * lam - 0.25 * lam * L - k * L * L * L / 6.0


@wp.func
def fixed_corotated_update(H: wp.mat33, mat: MaterialStruct, plastic: float, dt: float):
    jm1 = det_minus_one(H)
    J = 1.0 + jm1
    vol = wp.diag(wp.vec3(volume_pressure(jm1, mat.lam, mat.lam + 2.0 * mat.mu)))
    if J > 0.0:
        # b - V = (b - I) - (V - I): both small, so the stress keeps full float32 precision.
        D = green_minus_identity(H)
        Vm = left_stretch_minus_identity(D, jm1)
        if is_finite(Vm[0, 0]):
            return H, 2.0 * mat.mu * (D - Vm) + vol, plastic
    U, sigma, Vr = rv_svd(EYE + H)
    tau = U * wp.diag(2.0 * mat.mu * wp.cw_mul(sigma, sigma - wp.vec3(1.0))) * wp.transpose(U)
    return H, tau + vol, plastic


@wp.func
def fixed_corotated_energy(H: wp.mat33, mat: MaterialStruct) -> float:
    U, sigma, V = rv_svd(EYE + H)
    jm1 = det_minus_one(H)
    d = sigma - wp.vec3(1.0)
    return mat.mu * wp.dot(d, d) + volume_energy(jm1, mat.lam, mat.lam + 2.0 * mat.mu)
