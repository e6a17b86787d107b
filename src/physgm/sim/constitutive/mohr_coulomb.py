"""Mohr-Coulomb plasticity with cohesion and zero dilatancy on Hencky strain (granular media).

Same elasticity, apex and flow rule as ``drucker_prager`` (StVK on eps = log(sigma); plastic
flow deviatoric, so the volume is kept; beyond the apex, tension cut-off), but the yield
surface is the Mohr-Coulomb hexagon itself, in principal Kirchhoff stresses t1 >= t2 >= t3:

    f = (t1 - t3) + (t1 + t3) sin(phi) - 2 c cos(phi) <= 0

Why not the Drucker-Prager cone: a circular cone can match the hexagon in one loading only.
The usual (Klar et al. 2016) cone passes through its triaxial-compression corners, and in plane
shear, where a non-dilatant material flows with t2 the mean of t1 and t3, it holds
max shear / pressure = 6 sin(phi) / (sqrt(3) (3 - sin(phi))), 0.82 at phi = 35 degrees, where
Mohr-Coulomb holds sin(phi) = 0.57: the sand of a collapsing column or an avalanche behaved as if
its friction angle were 55 degrees. The hexagon gives every loading the friction angle the
material table states.

Return mapping at fixed volume, plastic potential t1 - t3 (flow (1, 0, -1) in principal strain),
with the corner returns of de Souza Neto, Peric & Owen (2008, section 8.2) when the projection
would reorder the principal values:
    main plane    dg = f13 / (4 mu): e1 -= dg, e3 += dg
    t1 = t2 edge  e1 -= a, e2 -= b, e3 += a + b, with
                  [4 mu, 2 mu (1 - s); 2 mu (1 - s), 4 mu] (a, b) = (f13, f23)
    t2 = t3 edge  e1 -= a + b, e2 += b, e3 += a, with
                  [4 mu, 2 mu (1 + s); 2 mu (1 + s), 4 mu] (a, b) = (f13, f12)
(s = sin(phi), fij the yield function of the principal pair i, j).
``plastic`` accumulates the plastic multipliers as a record.
"""

from __future__ import annotations

import warp as wp

from physgm.sim.constitutive.common import MaterialStruct, hencky_apex_return, hencky_decompose, hencky_finish


@wp.func
def mc_yield(hi: float, lo: float, tr: float, mat: MaterialStruct) -> float:
    """f of the principal pair (hi, lo) of log strains, Pa; ``tr`` the volumetric strain."""
    shift = (2.0 / 3.0) * (3.0 * mat.lam + 2.0 * mat.mu) * mat.tension_strain  # 2 c cos(phi) / sin(phi)
    return 2.0 * mat.mu * (hi - lo) + mat.sin_phi * (2.0 * mat.mu * (hi + lo) + 2.0 * mat.lam * tr - shift)


@wp.func
def mohr_coulomb_project(eps: wp.vec3, mat: MaterialStruct):
    """Return-mapped principal log strain and the plastic multiplier."""
    tr = eps[0] + eps[1] + eps[2]
    if tr >= mat.tension_strain:
        return wp.vec3(mat.tension_strain / 3.0), wp.length(eps - wp.vec3(tr / 3.0)) + tr - mat.tension_strain
    # Indices of the largest, middle and smallest principal strain (stress has the same order).
    i1 = 0
    i3 = 0
    for k in range(1, 3):
        if eps[k] > eps[i1]:
            i1 = k
        if eps[k] < eps[i3]:
            i3 = k
    if i1 == i3:
        return eps, 0.0  # hydrostatic
    i2 = 3 - i1 - i3
    e1 = eps[i1]
    e2 = eps[i2]
    e3 = eps[i3]
    f13 = mc_yield(e1, e3, tr, mat)
    if f13 <= 0.0:
        return eps, 0.0
    mu = mat.mu
    s = mat.sin_phi
    dg = f13 / (4.0 * mu)
    n1 = e1 - dg
    n2 = e2
    n3 = e3 + dg
    total = dg
    if n1 < e2:  # the largest two meet: return to the t1 = t2 edge
        f23 = mc_yield(e2, e3, tr, mat)
        c = 2.0 * mu * (1.0 - s)
        det = 16.0 * mu * mu - c * c
        a = (4.0 * mu * f13 - c * f23) / det
        b = (4.0 * mu * f23 - c * f13) / det
        n1 = e1 - a
        n2 = e2 - b
        n3 = e3 + a + b
        total = a + b
    elif n3 > e2:  # the smallest two meet: return to the t2 = t3 edge
        f12 = mc_yield(e1, e2, tr, mat)
        c = 2.0 * mu * (1.0 + s)
        det = 16.0 * mu * mu - c * c
        a = (4.0 * mu * f13 - c * f12) / det
        b = (4.0 * mu * f12 - c * f13) / det
        n1 = e1 - a - b
        n2 = e2 + b
        n3 = e3 + a
        total = a + b
    if n1 < n3:  # past every corner (only near the apex): no shear stress is left
        n1 = tr / 3.0
        n2 = tr / 3.0
        n3 = tr / 3.0
    out = wp.vec3(0.0)
    out[i1] = n1
    out[i2] = n2
    out[i3] = n3
    return out, total


@wp.func
def mohr_coulomb_update(H: wp.mat33, mat: MaterialStruct, plastic: float, dt: float):
    # Past the apex (grains pulled apart, most of a spreading sand) no eigenvectors are needed.
    apex, H_apex, tau_apex, dgamma_apex = hencky_apex_return(H, mat)
    if apex:
        return H_apex, tau_apex, plastic + dgamma_apex
    U, sigma, eps, clamped = hencky_decompose(H)
    eps_new, dgamma = mohr_coulomb_project(eps, mat)
    H_new, tau = hencky_finish(H, U, sigma, eps, eps_new, clamped or dgamma > 0.0, clamped, mat.mu, mat.lam)
    return H_new, tau, plastic + dgamma
