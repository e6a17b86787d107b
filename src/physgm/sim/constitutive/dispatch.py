"""One Warp entry point over all constitutive models, switched on the integer model id."""

from __future__ import annotations

import warp as wp

from physgm.sim.constitutive.common import (
    DRUCKER_PRAGER,
    FIXED_COROTATED,
    FLUID,
    FOAM,
    MOHR_COULOMB,
    NEO_HOOKEAN,
    VON_MISES,
    MaterialStruct,
    hencky_model_energy,
)
from physgm.sim.constitutive.drucker_prager import drucker_prager_update
from physgm.sim.constitutive.fixed_corotated import fixed_corotated_energy, fixed_corotated_update
from physgm.sim.constitutive.fluid import fluid_energy, fluid_update
from physgm.sim.constitutive.foam import foam_update
from physgm.sim.constitutive.mohr_coulomb import mohr_coulomb_update
from physgm.sim.constitutive.neo_hookean import neo_hookean_energy, neo_hookean_update
from physgm.sim.constitutive.von_mises import von_mises_update


@wp.func
def constitutive_update(H: wp.mat33, mat: MaterialStruct, plastic: float, dt: float):
    """Return mapping + Kirchhoff stress of F = I + H: (H_new, tau [Pa], plastic_new)."""
    if mat.model == FIXED_COROTATED:
        return fixed_corotated_update(H, mat, plastic, dt)
    if mat.model == NEO_HOOKEAN:
        return neo_hookean_update(H, mat, plastic, dt)
    if mat.model == DRUCKER_PRAGER:
        return drucker_prager_update(H, mat, plastic, dt)
    if mat.model == MOHR_COULOMB:
        return mohr_coulomb_update(H, mat, plastic, dt)
    if mat.model == VON_MISES:
        return von_mises_update(H, mat, plastic, dt)
    if mat.model == FOAM:
        return foam_update(H, mat, plastic, dt)
    return fluid_update(H, mat, plastic, dt)


# Each model's return mapping by id: ``kernels.g2p_kernel`` compiles a g2p for one model with it.
UPDATES = {
    FIXED_COROTATED: fixed_corotated_update,
    NEO_HOOKEAN: neo_hookean_update,
    DRUCKER_PRAGER: drucker_prager_update,
    MOHR_COULOMB: mohr_coulomb_update,
    VON_MISES: von_mises_update,
    FOAM: foam_update,
    FLUID: fluid_update,
}


def update_for(models: tuple[int, ...]) -> wp.Function:
    """The return mapping for particles of these model ids: one model's own, else the switch."""
    unknown = set(models) - set(UPDATES)
    if unknown or not models:
        raise ValueError(f"model ids must be a non-empty subset of {sorted(UPDATES)}, got {models}")
    return UPDATES[models[0]] if len(set(models)) == 1 else constitutive_update


@wp.func
def energy_density(H: wp.mat33, mat: MaterialStruct) -> float:
    """Strain energy per unit rest volume of F = I + H, J/m^3 (H keeps small strains exact)."""
    if mat.model == FIXED_COROTATED:
        return fixed_corotated_energy(H, mat)
    if mat.model == NEO_HOOKEAN:
        return neo_hookean_energy(H, mat)
    if mat.model == FLUID:
        return fluid_energy(H, mat)
    # Drucker-Prager, Mohr-Coulomb, von Mises and foam: Hencky strain, one energy
    return hencky_model_energy(H, mat)
