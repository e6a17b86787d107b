"""Distribution of the true physics in the synthetic data set, per material.

E and nu are drawn from the material's typical ranges in the simulator's material table
(``physgm.physics.materials``: ``E_range``, ``nu_range``), E log-uniform and nu uniform. The
density spread of the synthetic set (the table holds one typical density) is the only data
prior kept here. The two uniform numbers behind E and nu (``stiffness`` and ``poisson`` in
[0, 1]) are returned too: the appearance and the shape use them as visible cues, so a model
can learn more than the per-material mean.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from physgm.physics.materials import MATERIAL_NAMES, get_material


def material_names() -> tuple[str, ...]:
    """The material class order of the model (``physgm.physics.materials.MATERIAL_NAMES``)."""
    return tuple(MATERIAL_NAMES)


def material_index(name: str) -> int:
    if name not in MATERIAL_NAMES:
        raise KeyError(f"unknown material {name!r}; known materials: {', '.join(MATERIAL_NAMES)}")
    return MATERIAL_NAMES.index(name)


# Density ranges of the synthetic set, kg/m^3 (light to dense woods, foams, metals...).
DENSITY_RANGES: dict[str, tuple[float, float]] = {
    "plastic": (900, 1400),
    "wood": (400, 900),
    "metal": (2700, 8900),
    "fabric": (150, 500),
    "ceramic": (2200, 3900),
    "stone": (2200, 3000),
    "paper": (600, 1100),
    "leather": (800, 1100),
    "glass": (2200, 2800),
    "rubber": (900, 1300),
    "foam": (20, 200),
    "snow": (100, 500),
    "sand": (1400, 1800),
    "jelly": (1000, 1100),
    "plasticine": (1200, 1800),
}


def constitutive_model(material: str) -> str:
    """The simulator's constitutive model name for ``material``."""
    return get_material(material).model


@dataclass(frozen=True)
class TruePhysics:
    """The physics an asset is simulated with, plus the uniform draws behind it."""

    material: str
    E: float  # Pa
    nu: float
    density: float  # kg/m^3
    stiffness: float  # in [0, 1]: position of log10 E in the material's range
    poisson: float  # in [0, 1]: position of nu in the material's range

    @property
    def log10_E(self) -> float:
        return math.log10(self.E)


def sample_physics(material: str, rng: np.random.Generator) -> TruePhysics:
    """Draw E (log-uniform), nu (uniform) in the material's typical ranges, and a density.

    Density rises with stiffness (half correlated), as it does across real woods, foams and metals.
    """
    spec = get_material(material)
    if material not in DENSITY_RANGES:
        raise KeyError(
            f"no synthetic density range for material {material!r}; add one to DENSITY_RANGES in {__name__}"
        )
    stiffness, poisson, extra = rng.random(3)
    lo, hi = math.log10(spec.E_range[0]), math.log10(spec.E_range[1])
    E = 10.0 ** (lo + stiffness * (hi - lo))
    nu = spec.nu_range[0] + poisson * (spec.nu_range[1] - spec.nu_range[0])
    rho_lo, rho_hi = DENSITY_RANGES[material]
    density = rho_lo + (0.5 * stiffness + 0.5 * extra) * (rho_hi - rho_lo)
    return TruePhysics(material, float(E), float(nu), float(density), float(stiffness), float(poisson))
