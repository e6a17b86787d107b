"""von Mises (J2) plasticity with linear isotropic hardening on Hencky strain.

Radial return (Simo and Hughes 1998, box 3.1) in principal log strain: with deviatoric trial
strain e = dev(eps), yield radius r = sqrt(2/3) (sigma_y + H kappa) / (2 mu), and accumulated
equivalent plastic strain kappa (the particle's ``plastic`` scalar):
    ||e|| <= r  -> elastic
    otherwise   -> dgamma = (||e|| - r) / (1 + H / (3 mu)),  e -= dgamma e/||e||,
                   kappa += sqrt(2/3) dgamma.
The volumetric part stays elastic (metals and plasticine keep their volume when they yield).
Whatever the yield radius, ||e|| never stays above ``common.HENCKY_DEV_MAX``, where the Hencky
energy stops being elliptic.
"""

from __future__ import annotations

import warp as wp

from physgm.sim.constitutive.common import (
    EYE,
    HENCKY_DEV_MAX,
    MaterialStruct,
    hencky_decompose,
    hencky_finish,
    hencky_small_strain,
    hencky_stress,
)

SQRT_2_3 = wp.constant(0.816496580927726)


@wp.func
def yield_radius(mat: MaterialStruct, kappa: float) -> float:
    """||dev eps|| at which the hardened yield surface is reached."""
    return SQRT_2_3 * (mat.yield_stress + mat.hardening * kappa) / (2.0 * mat.mu)


@wp.func
def von_mises_project(eps: wp.vec3, mat: MaterialStruct, kappa: float, viscous_term: float):
    """Radial return; ``viscous_term`` eta / (2 mu dt) turns it into a Perzyna (foam) update."""
    tr = eps[0] + eps[1] + eps[2]
    dev = eps - wp.vec3(tr / 3.0)
    dev_norm = wp.length(dev)
    radius = yield_radius(mat, kappa)
    if dev_norm <= wp.min(radius, HENCKY_DEV_MAX):
        return eps, kappa
    dgamma = wp.max(dev_norm - radius, 0.0) / (1.0 + mat.hardening / (3.0 * mat.mu) + viscous_term)
    # Never past the Hencky law's elliptic range, however high the yield stress or the viscosity.
    dgamma = wp.max(dgamma, dev_norm - HENCKY_DEV_MAX)
    return eps - (dgamma / dev_norm) * dev, kappa + SQRT_2_3 * dgamma


@wp.func
def von_mises_return(H: wp.mat33, mat: MaterialStruct, plastic: float, viscous_term: float):
    """``update`` with the radial return of `von_mises_project`: (H_new, tau [Pa], kappa_new).

    An elastic strain up to ~15 % (the body at rest or ringing, most particles between impacts) is
    decided on the strain as a matrix (``hencky_small_strain``); only a larger or yielding one
    needs the eigenvectors."""
    small, eps_m = hencky_small_strain(H)
    if small:
        dev = eps_m - (wp.trace(eps_m) / 3.0) * EYE
        radius = yield_radius(mat, plastic)
        if wp.ddot(dev, dev) <= radius * radius:
            return H, hencky_stress(eps_m, mat.mu, mat.lam), plastic
    U, sigma, eps, clamped = hencky_decompose(H)
    eps_new, kappa = von_mises_project(eps, mat, plastic, viscous_term)
    H_new, tau = hencky_finish(
        H, U, sigma, eps, eps_new, clamped or kappa > plastic, clamped, mat.mu, mat.lam
    )
    return H_new, tau, kappa


@wp.func
def von_mises_update(H: wp.mat33, mat: MaterialStruct, plastic: float, dt: float):
    return von_mises_return(H, mat, plastic, 0.0)
