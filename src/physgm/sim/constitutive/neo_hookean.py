"""Compressible Neo-Hookean elasticity with a linear log extension and a volume barrier.

psi = mu/2 (tr(F^T F) - 3) - mu g(J) + lam/2 g(J)^2, where g(J) = log J for J >= J_E and, below
J_E, its tangent line g(J) = log J_E + (J - J_E) / J_E. g is C^1, so the stress is continuous; it
is finite for every J, so energy and stress stay finite for degenerate (J = 0) and inverted
(J < 0) elements; d psi / dJ = (lam g - mu) g' < 0 below J_E, so the energy keeps growing as the
volume collapses and pushes inverted elements back; and the volumetric stiffness lam / J_E^2
below J_E stays below the log branch's at J_E (no CFL surprise). Above J_E this is exactly the
classic model (e.g. Bonet and Wood): tau = mu (F F^T - I) + lam log(J) I. In general
tau = P F^T = mu F F^T + (lam g(J) - mu) g'(J) J I (no decomposition needed), evaluated in H = F - I.

The extension alone is no barrier: its Kirchhoff pressure returns to mu at J = 0, so a crushed
particle is not pushed back, and a nu = 0.01 cube hit at twice its wave speed inverted (issue 24).
Below J_E we add p_b(J) = -(k/2) log(J / J_E)^2 with k = lam + 2 mu (the same barrier as
fixed_corotated's, zero value and slope at J_E, so the model stays C^1), whose energy
-k log(J / J_E)^3 / 6 grows without bound as J -> 0. The stress is the energy gradient for J > 0;
a step reaching J <= 0 is rejected by the divergence guard, and J is clamped to J_FLOOR in the
barrier so the rejected state stays finite.
"""

from __future__ import annotations

import warp as wp

from physgm.sim.constitutive.common import MaterialStruct, det_minus_one, green_minus_identity, log1p

J_E = wp.constant(0.1)  # switch point of the log extension and the barrier (10 % of the rest volume)
J_FLOOR = wp.constant(1.0e-6)  # the barrier's log is clamped here (J <= 0 is a rejected step)


@wp.func
def barrier_log(J: float) -> float:
    """log(J / J_E) below J_E (clamped at J_FLOOR), 0 above."""
    if J >= J_E:
        return 0.0
    return wp.log(wp.max(J, J_FLOOR) / J_E)


@wp.func
def log_ext(J: float) -> float:
    if J >= J_E:
        return wp.log(J)
    return wp.log(J_E) + (J - J_E) / J_E


@wp.func
def log_ext_derivative(J: float) -> float:
    if J >= J_E:
        return 1.0 / J
    return 1.0 / J_E


@wp.func
def neo_hookean_update(H: wp.mat33, mat: MaterialStruct, plastic: float, dt: float):
    # tau = mu b + (lam g - mu) g' J I = mu (b - I) + (mu + (lam g - mu) g' J) I, which for
    # J >= J_E is mu (b - I) + lam log(J) I: no O(mu) terms that cancel.
    jm1 = det_minus_one(H)
    J = 1.0 + jm1
    p = 0.0
    if J >= J_E:
        p = mat.lam * log1p(jm1)
    else:
        L = barrier_log(J)
        p = mat.mu + (mat.lam * log_ext(J) - mat.mu) * log_ext_derivative(J) * J
        p = p - 0.5 * (mat.lam + 2.0 * mat.mu) * L * L
    return H, mat.mu * green_minus_identity(H) + wp.diag(wp.vec3(p)), plastic


@wp.func
def neo_hookean_energy(H: wp.mat33, mat: MaterialStruct) -> float:
    """Energy density of F = I + H, written in H: the terms of size mu |H| cancel to O(|H|^2)."""
    jm1 = det_minus_one(H)
    J = 1.0 + jm1
    g = log_ext(J)
    if J >= J_E:
        g = log1p(jm1)
    trc_minus_3 = 2.0 * wp.trace(H) + wp.ddot(H, H)  # tr(F^T F) - 3
    L = barrier_log(J)
    barrier = -(mat.lam + 2.0 * mat.mu) * L * L * L / 6.0
    return 0.5 * mat.mu * trc_minus_3 - mat.mu * g + 0.5 * mat.lam * g * g + barrier
