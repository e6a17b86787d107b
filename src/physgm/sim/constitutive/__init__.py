"""Constitutive models: one registry (name -> model id + parameter packer) and their parameters.

Models (one module each; numpy twins in ``reference.py``):
    fixed_corotated  elastic, Stomakhin et al. 2012
    neo_hookean      elastic, inversion-safe log extension below J = 0.1
    drucker_prager   Klar et al. 2016 sand plasticity on Hencky strain, with cohesion
    mohr_coulomb     the same with the Mohr-Coulomb hexagon for the cone (sand, snow; see its module)
    von_mises        J2 plasticity with linear hardening on Hencky strain
    foam             Perzyna viscoplastic von Mises (rate-dependent yield)
    fluid            weakly compressible fluid, J-based pressure, F reset to J^(1/3) I
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

from physgm.sim.constitutive import common
from physgm.sim.constitutive.common import MaterialStruct


@dataclass(frozen=True)
class MaterialParams:
    """Solver-level parameters of one material, SI units. Validated on construction."""

    model: str  # name in MODELS
    E: float  # Young's modulus, Pa
    nu: float  # Poisson ratio, (-1, 0.5)
    density: float  # rest density, kg/m^3
    yield_stress: float = 0.0  # von_mises / foam initial yield stress, Pa
    hardening: float = 0.0  # linear isotropic hardening modulus, Pa
    friction_angle: float = 0.0  # drucker_prager / mohr_coulomb friction angle phi, degrees
    cohesion: float = 0.0  # drucker_prager / mohr_coulomb cohesion c, Pa
    viscosity: float = 0.0  # foam Perzyna viscosity, Pa s

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"unknown constitutive model {self.model!r}; known models: {', '.join(MODELS)}")
        _check(
            math.isfinite(self.E) and self.E > 0.0, f"Young's modulus E={self.E!r} Pa must be finite and > 0"
        )
        _check(
            math.isfinite(self.nu) and -1.0 < self.nu < 0.5,
            f"Poisson ratio nu={self.nu!r} must lie in (-1, 0.5); 0.5 is incompressible and not supported",
        )
        _check(
            math.isfinite(self.density) and self.density > 0.0, f"density={self.density!r} kg/m^3 must be > 0"
        )
        for name in ("yield_stress", "hardening", "cohesion", "viscosity"):
            value = getattr(self, name)
            _check(math.isfinite(value) and value >= 0.0, f"{name}={value!r} must be finite and >= 0")
        MODELS[self.model].validate(self)

    @property
    def mu(self) -> float:
        """Shear modulus, Pa."""
        return self.E / (2.0 * (1.0 + self.nu))

    @property
    def lam(self) -> float:
        """First Lame parameter, Pa."""
        return self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))

    @property
    def bulk(self) -> float:
        """Bulk modulus K = E / (3 (1 - 2 nu)), Pa."""
        return self.E / (3.0 * (1.0 - 2.0 * self.nu))

    def wave_speed(self) -> float:
        """P-wave speed sqrt((lam + 2 mu) / rho) in m/s, the CFL speed of the model."""
        return math.sqrt(MODELS[self.model].stiffness(self) / self.density)

    def with_elasticity(self, E: float | None = None, nu: float | None = None) -> MaterialParams:
        """Copy with another E and/or nu (validated)."""
        return replace(self, E=self.E if E is None else float(E), nu=self.nu if nu is None else float(nu))

    def pack(self) -> MaterialStruct:
        """The kernel-side struct of this material."""
        s = MaterialStruct()
        s.model = MODELS[self.model].id
        s.mu = self.mu
        s.lam = self.lam
        s.yield_stress = self.yield_stress
        s.hardening = self.hardening
        s.viscosity = self.viscosity
        s.bulk = self.bulk
        s.j_floor = MODELS[self.model].j_floor
        if self.model in ("drucker_prager", "mohr_coulomb"):
            sin_phi = math.sin(math.radians(self.friction_angle))
            s.alpha = math.sqrt(2.0 / 3.0) * 2.0 * sin_phi / (3.0 - sin_phi)
            s.sin_phi = sin_phi
            cot_phi = 1.0 / math.tan(math.radians(self.friction_angle))
            s.tension_strain = 3.0 * self.cohesion * cot_phi / (3.0 * self.lam + 2.0 * self.mu)
        return s


def _check(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


@dataclass(frozen=True)
class ConstitutiveModel:
    """Registry entry: kernel id, the stiffness that sets the CFL speed, extra validation, J floor.

    ``j_floor`` bounds det F of the *elastic* trial state (F after the step, before the return
    mapping): the divergence guard rejects a step that takes any particle of the model below it
    and retries with a smaller one. It is per model because what a model can represent differs,
    and on the elastic part so that plastic compaction (which the return mappings put into the
    plastic history, not into F) is never rejected. 0 for every model means an inverted or
    collapsed element (J <= 0) is always a failed step, never a state.
    """

    name: str
    id: int
    stiffness: Callable[[MaterialParams], float]  # P-wave modulus, Pa
    validate: Callable[[MaterialParams], None]
    plastic: bool  # has a return mapping
    j_floor: float = 0.0


def _p_modulus(p: MaterialParams) -> float:
    return p.lam + 2.0 * p.mu


def _no_extra(p: MaterialParams) -> None:
    return None


def _needs_yield(p: MaterialParams) -> None:
    _check(p.yield_stress > 0.0, f"model {p.model!r} needs yield_stress > 0 Pa, got {p.yield_stress!r}")


def _needs_friction(p: MaterialParams) -> None:
    _check(
        0.0 < p.friction_angle < 90.0,
        f"{p.model} needs 0 < friction_angle < 90 degrees, got {p.friction_angle!r}",
    )


MODELS: dict[str, ConstitutiveModel] = {
    m.name: m
    for m in (
        # The volume barrier holds down to its pressure clamp at J = 1e-6; 1e-4 stays well inside
        # it (float32 J still has three digits) and costs 100 lam of energy density, more than
        # an impact below ~10x the wave speed brings: a step reaching it overshot.
        ConstitutiveModel(
            "fixed_corotated", int(common.FIXED_COROTATED), _p_modulus, _no_extra, False, j_floor=1.0e-4
        ),
        ConstitutiveModel("neo_hookean", int(common.NEO_HOOKEAN), _p_modulus, _no_extra, False),
        ConstitutiveModel("drucker_prager", int(common.DRUCKER_PRAGER), _p_modulus, _needs_friction, True),
        ConstitutiveModel("mohr_coulomb", int(common.MOHR_COULOMB), _p_modulus, _needs_friction, True),
        ConstitutiveModel("von_mises", int(common.VON_MISES), _p_modulus, _needs_yield, True),
        ConstitutiveModel("foam", int(common.FOAM), _p_modulus, _needs_yield, True),
        # A fluid has no shear stiffness: its sound speed is sqrt(K / rho).
        ConstitutiveModel("fluid", int(common.FLUID), lambda p: p.bulk, _no_extra, False),
    )
}

__all__ = ["MODELS", "ConstitutiveModel", "MaterialParams", "MaterialStruct"]
