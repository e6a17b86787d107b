"""Drucker-Prager plasticity with cohesion on Hencky strain (Klar et al. 2016, sand).

Elasticity is StVK on the Hencky strain eps = log(sigma): tau = 2 mu eps + lam tr(eps) (principal).
The yield cone ||dev tau|| <= 3 alpha (p + c cot(phi)), p = -tr(tau)/3, with
alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi)) (compression match of Mohr-Coulomb) and cohesion c,
in strain space (Klar et al. 2016, section 4.2, with the apex shifted by the cohesion):
    eps_t = 3 c cot(phi) / (3 lam + 2 mu)                          (apex, >= 0; 0 for sand)
    tr(eps) >= eps_t                      -> eps = eps_t / 3 (1, 1, 1)  (apex: tension cut-off)
    dgamma = ||dev eps|| + alpha (3 lam + 2 mu) / (2 mu) (tr(eps) - eps_t)
    dgamma <= 0                           -> elastic, unchanged
    otherwise                             -> eps -= dgamma dev(eps) / ||dev eps||
The friction angle is constant (no Klar hardening); ``plastic`` accumulates dgamma as a record.
"""

from __future__ import annotations

import warp as wp

from physgm.sim.constitutive.common import (
    EYE,
    MaterialStruct,
    hencky_apex_return,
    hencky_decompose,
    hencky_finish,
    hencky_small_strain,
    hencky_stress,
)


@wp.func
def cone_multiplier(tr: float, dev_norm: float, mat: MaterialStruct) -> float:
    """dgamma of the module docstring from the strain's invariants: > 0 outside the cone."""
    return dev_norm + mat.alpha * (3.0 * mat.lam + 2.0 * mat.mu) / (2.0 * mat.mu) * (tr - mat.tension_strain)


@wp.func
def drucker_prager_project(eps: wp.vec3, mat: MaterialStruct):
    """Return-mapped principal log strain and the plastic multiplier."""
    tr = eps[0] + eps[1] + eps[2]
    if tr >= mat.tension_strain:
        delta = tr - mat.tension_strain
        return wp.vec3(mat.tension_strain / 3.0), wp.length(eps - wp.vec3(tr / 3.0)) + delta
    dev = eps - wp.vec3(tr / 3.0)
    dev_norm = wp.length(dev)
    dgamma = cone_multiplier(tr, dev_norm, mat)
    if dgamma <= 0.0 or dev_norm <= 0.0:
        return eps, 0.0
    return eps - (dgamma / dev_norm) * dev, dgamma


@wp.func
def drucker_prager_update(H: wp.mat33, mat: MaterialStruct, plastic: float, dt: float):
    # A strain up to ~15 % inside the cone (a resting pile's interior) needs no eigenvectors
    # (``hencky_small_strain``); the cone test is on invariants.
    small, eps_m = hencky_small_strain(H)
    if small:
        tr = wp.trace(eps_m)
        dev = eps_m - (tr / 3.0) * EYE
        dev_norm = wp.sqrt(wp.ddot(dev, dev))
        if tr < mat.tension_strain and (dev_norm <= 0.0 or cone_multiplier(tr, dev_norm, mat) <= 0.0):
            return H, hencky_stress(eps_m, mat.mu, mat.lam), plastic
    apex, H_apex, tau_apex, dgamma_apex = hencky_apex_return(H, mat)  # past the apex: no eigenvectors
    if apex:
        return H_apex, tau_apex, plastic + dgamma_apex
    U, sigma, eps, clamped = hencky_decompose(H)
    eps_new, dgamma = drucker_prager_project(eps, mat)
    H_new, tau = hencky_finish(H, U, sigma, eps, eps_new, clamped or dgamma > 0.0, clamped, mat.mu, mat.lam)
    return H_new, tau, plastic + dgamma
