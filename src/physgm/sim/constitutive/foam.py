"""Viscoplastic foam: Perzyna-type viscoplastic von Mises with linear hardening (Hencky strain).

The overstress above the von Mises yield surface relaxes at a finite rate set by the viscosity
eta (Pa s) instead of being removed at once (Simo and Hughes 1998, section 2.7, Perzyna model
discretised by backward Euler). In the radial return of ``von_mises`` the plastic multiplier
becomes
    dgamma = (||e|| - r) / (1 + H / (3 mu) + eta / (2 mu dt)),
so eta -> 0 is rate-independent von Mises and eta -> infinity is purely elastic up to a deviatoric
Hencky strain of ``common.HENCKY_DEV_MAX``, beyond which the return is rate-independent: the
Hencky energy is not elliptic there (docs/measurements_sim.md, section 9). Foams squash and
slowly keep their new shape, which is this behaviour; volumetric crushing is not modelled.
"""

from __future__ import annotations

import warp as wp

from physgm.sim.constitutive.common import MaterialStruct
from physgm.sim.constitutive.von_mises import von_mises_return


@wp.func
def foam_update(H: wp.mat33, mat: MaterialStruct, plastic: float, dt: float):
    viscous_term = 0.0
    if dt > 0.0:
        viscous_term = mat.viscosity / (2.0 * mat.mu * dt)
    return von_mises_return(H, mat, plastic, viscous_term)
