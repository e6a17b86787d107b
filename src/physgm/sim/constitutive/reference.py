"""Plain numpy twins of the constitutive models, float64, for tests only.

Written independently of the Warp code: stretches come from ``np.linalg.svd`` (made rotation
variant), stresses from the textbook formulas. Shapes: F [N, 3, 3]; returns (F_new, tau, plastic).
"""

from __future__ import annotations

import math

import numpy as np

SIGMA_MIN = 1.0e-3
HENCKY_DEV_MAX = 1.0  # largest elastic ||dev log stretch|| of von Mises / foam (common.HENCKY_DEV_MAX)
J_E = 0.1
J_MIN_FLUID = 0.05


def rv_svd(F: np.ndarray):  # F: [N, 3, 3]
    """Rotation-variant SVD: det U = det V = +1, the smallest singular value carries det's sign."""
    U, s, Vt = np.linalg.svd(F)
    U, s, Vt = U.copy(), s.copy(), Vt.copy()
    flip_u = np.linalg.det(U) < 0
    U[flip_u, :, 2] *= -1
    s[flip_u, 2] *= -1
    flip_v = np.linalg.det(Vt) < 0
    Vt[flip_v, 2, :] *= -1
    s[flip_v, 2] *= -1
    return U, s, Vt


def _diag_sandwich(U: np.ndarray, d: np.ndarray, Vt: np.ndarray) -> np.ndarray:
    return np.einsum("nij,nj,njk->nik", U, d, Vt)


FC_J_B, FC_J_FLOOR = 0.5, 1.0e-6  # fixed_corotated's volume barrier (see its Warp module)


def fc_volume_pressure(J, lam, k):
    """p(J) = J psi_vol'(J): lam (J - 1) J above J_B, -lam/4 - k/2 log(J / J_B)^2 below (k = lam + 2 mu)."""
    L = np.log(np.maximum(J, FC_J_FLOOR) / FC_J_B)
    return np.where(J >= FC_J_B, lam * (J - 1) * J, -0.25 * lam - 0.5 * k * L**2)


def fc_volume_energy(J, lam, k):
    L = np.log(np.maximum(J, FC_J_FLOOR) / FC_J_B)
    return np.where(J >= FC_J_B, 0.5 * lam * (J - 1) ** 2, lam / 8 - lam * L / 4 - k * L**3 / 6)


def nh_barrier_log(J):
    """log(J / J_E) below J_E (J clamped at 1e-6), 0 above: neo_hookean's volume barrier."""
    return np.where(J >= J_E, 0.0, np.log(np.maximum(J, 1.0e-6) / J_E))


def fixed_corotated(F, mu, lam, plastic=None, dt=0.0):
    U, s, Vt = rv_svd(F)
    R = U @ Vt
    J = np.linalg.det(F)
    p = fc_volume_pressure(J, lam, lam + 2 * mu)
    tau = 2 * mu * (F - R) @ np.swapaxes(F, 1, 2) + p[:, None, None] * np.eye(3)
    return F.copy(), tau, plastic


def _g(J):
    return np.where(J >= J_E, np.log(np.maximum(J, J_E)), math.log(J_E) + (J - J_E) / J_E)


def _dg(J):
    return np.where(J >= J_E, 1.0 / np.maximum(J, J_E), 1.0 / J_E)


def cofactor(F):
    return np.stack(
        [
            np.cross(F[:, :, 1], F[:, :, 2]),
            np.cross(F[:, :, 2], F[:, :, 0]),
            np.cross(F[:, :, 0], F[:, :, 1]),
        ],
        axis=2,
    )


def neo_hookean_first_pk(F, mu, lam):
    """P = mu F + (lam g(J) - mu) g'(J) cof(F), defined for every F (cof F = J F^-T)."""
    J = np.linalg.det(F)
    return mu * F + ((lam * _g(J) - mu) * _dg(J))[:, None, None] * cofactor(F)


def neo_hookean(F, mu, lam, plastic=None, dt=0.0):
    barrier = -0.5 * (lam + 2 * mu) * nh_barrier_log(np.linalg.det(F)) ** 2  # Kirchhoff pressure
    tau = neo_hookean_first_pk(F, mu, lam) @ np.swapaxes(F, 1, 2) + barrier[:, None, None] * np.eye(3)
    return F.copy(), tau, plastic


def _hencky(F):
    U, s, Vt = rv_svd(F)
    return U, Vt, np.log(np.maximum(s, SIGMA_MIN))


def _hencky_out(U, Vt, eps, mu, lam):
    F_new = _diag_sandwich(U, np.exp(eps), Vt)
    tau = _diag_sandwich(U, 2 * mu * eps + lam * eps.sum(1, keepdims=True), np.swapaxes(U, 1, 2))
    return F_new, tau


def drucker_prager(F, mu, lam, friction_angle, cohesion, plastic, dt=0.0):
    """Klar et al. 2016 projection with the apex shifted by the cohesion."""
    U, Vt, eps = _hencky(F)
    sin_phi = math.sin(math.radians(friction_angle))
    alpha = math.sqrt(2 / 3) * 2 * sin_phi / (3 - sin_phi)
    eps_t = 3 * cohesion / math.tan(math.radians(friction_angle)) / (3 * lam + 2 * mu)
    out = eps.copy()
    dgamma = np.zeros(len(F))
    for n in range(len(F)):
        tr = eps[n].sum()
        dev = eps[n] - tr / 3
        norm = np.linalg.norm(dev)
        if tr >= eps_t:
            out[n] = eps_t / 3
            dgamma[n] = norm + tr - eps_t
            continue
        dg = norm + alpha * (3 * lam + 2 * mu) / (2 * mu) * (tr - eps_t)
        if dg > 0 and norm > 0:
            out[n] = eps[n] - dg * dev / norm
            dgamma[n] = dg
    F_new, tau = _hencky_out(U, Vt, out, mu, lam)
    return F_new, tau, plastic + dgamma


def mohr_coulomb(F, mu, lam, friction_angle, cohesion, plastic, dt=0.0):
    """Mohr-Coulomb return at fixed volume (main plane, then the two edges; ``mohr_coulomb.py``)."""
    U, Vt, eps = _hencky(F)
    s = math.sin(math.radians(friction_angle))
    eps_t = 3 * cohesion / math.tan(math.radians(friction_angle)) / (3 * lam + 2 * mu)
    shift = 2 / 3 * (3 * lam + 2 * mu) * eps_t

    def f(hi, lo, tr):
        return 2 * mu * (hi - lo) + s * (2 * mu * (hi + lo) + 2 * lam * tr - shift)

    out = eps.copy()
    dgamma = np.zeros(len(F))
    for n in range(len(F)):
        e, tr = eps[n], eps[n].sum()
        if tr >= eps_t:
            out[n] = eps_t / 3
            dgamma[n] = np.linalg.norm(e - tr / 3) + tr - eps_t
            continue
        i3, i2, i1 = np.argsort(e, kind="stable")
        e1, e2, e3 = e[i1], e[i2], e[i3]
        f13 = f(e1, e3, tr)
        if e1 == e3 or f13 <= 0:
            continue
        dg = f13 / (4 * mu)
        new = np.array([e1 - dg, e2, e3 + dg])
        total = dg
        if new[0] < e2:
            c = 2 * mu * (1 - s)
            a, b = np.linalg.solve([[4 * mu, c], [c, 4 * mu]], [f13, f(e2, e3, tr)])
            new, total = np.array([e1 - a, e2 - b, e3 + a + b]), a + b
        elif new[2] > e2:
            c = 2 * mu * (1 + s)
            a, b = np.linalg.solve([[4 * mu, c], [c, 4 * mu]], [f13, f(e1, e2, tr)])
            new, total = np.array([e1 - a - b, e2 + b, e3 + a]), a + b
        if new[0] < new[2]:
            new = np.full(3, tr / 3)
        out[n, [i1, i2, i3]] = new
        dgamma[n] = total
    F_new, tau = _hencky_out(U, Vt, out, mu, lam)
    return F_new, tau, plastic + dgamma


def von_mises(F, mu, lam, yield_stress, hardening, plastic, dt=0.0, viscosity=0.0):
    """Radial return with linear hardening; viscosity > 0 gives the Perzyna (foam) update."""
    U, Vt, eps = _hencky(F)
    out = eps.copy()
    kappa = plastic.copy()
    viscous = viscosity / (2 * mu * dt) if viscosity > 0 else 0.0
    for n in range(len(F)):
        dev = eps[n] - eps[n].sum() / 3
        norm = np.linalg.norm(dev)
        radius = math.sqrt(2 / 3) * (yield_stress + hardening * plastic[n]) / (2 * mu)
        if norm > min(radius, HENCKY_DEV_MAX):
            dg = max(norm - radius, 0.0) / (1 + hardening / (3 * mu) + viscous)
            dg = max(dg, norm - HENCKY_DEV_MAX)
            out[n] = eps[n] - dg * dev / norm
            kappa[n] = plastic[n] + math.sqrt(2 / 3) * dg
    F_new, tau = _hencky_out(U, Vt, out, mu, lam)
    return F_new, tau, kappa


def fluid(F, bulk, plastic=None, dt=0.0):
    J = np.maximum(np.linalg.det(F), J_MIN_FLUID)
    F_new = np.cbrt(J)[:, None, None] * np.eye(3)
    return F_new, (bulk * (J - 1))[:, None, None] * np.eye(3), plastic


def energy_density(model: str, F: np.ndarray, mu: float, lam: float, bulk: float = 0.0) -> np.ndarray:
    """Strain energy per rest volume, J/m^3, for every model of the registry."""
    J = np.linalg.det(F)
    if model == "fixed_corotated":
        s = rv_svd(F)[1]
        return mu * ((s - 1) ** 2).sum(1) + fc_volume_energy(J, lam, lam + 2 * mu)
    if model == "neo_hookean":
        g = _g(J)
        barrier = -(lam + 2 * mu) * nh_barrier_log(J) ** 3 / 6
        return 0.5 * mu * ((F**2).sum((1, 2)) - 3) - mu * g + 0.5 * lam * g**2 + barrier
    if model == "fluid":
        Jc = np.maximum(J, J_MIN_FLUID)  # the states the solver keeps are clamped there
        return bulk * (Jc - 1 - np.log(Jc))
    eps = _hencky(F)[2]
    return mu * (eps**2).sum(1) + 0.5 * lam * eps.sum(1) ** 2


def update(params, F: np.ndarray, plastic: np.ndarray, dt: float):
    """Dispatch on a ``MaterialParams``: (F_new, tau, plastic_new)."""
    mu, lam = params.mu, params.lam
    if params.model == "fixed_corotated":
        return fixed_corotated(F, mu, lam, plastic)
    if params.model == "neo_hookean":
        return neo_hookean(F, mu, lam, plastic)
    if params.model == "drucker_prager":
        return drucker_prager(F, mu, lam, params.friction_angle, params.cohesion, plastic)
    if params.model == "mohr_coulomb":
        return mohr_coulomb(F, mu, lam, params.friction_angle, params.cohesion, plastic)
    if params.model == "von_mises":
        return von_mises(F, mu, lam, params.yield_stress, params.hardening, plastic)
    if params.model == "foam":
        return von_mises(F, mu, lam, params.yield_stress, params.hardening, plastic, dt, params.viscosity)
    if params.model == "fluid":
        return fluid(F, params.bulk, plastic)
    raise ValueError(f"no reference for model {params.model!r}")
