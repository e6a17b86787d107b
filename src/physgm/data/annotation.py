"""Coarse physical labels as an automatic (vision-language) annotator would give them.

The PhysGM authors label their assets with a model that picks one of 10 categories for Young's
modulus and for Poisson's ratio. The synthetic generator imitates that annotator on top of the
true continuous physics: quantise, add a per-material systematic bias, move a configurable
fraction of labels to a neighbouring category, and sometimes confuse look-alike materials.
Training on these labels while scoring against the true values is what lets the DPO stage
show a gain over supervised pretraining.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# The paper's categories (Pa and dimensionless); class index = position in these tuples.
E_CATEGORIES: tuple[float, ...] = (1e3, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 7e10, 2e11, 4e11)
NU_CATEGORIES: tuple[float, ...] = (0.01, 0.10, 0.15, 0.20, 0.25, 0.30, 0.35, 0.40, 0.45, 0.49)
_LOG_E = np.log10(np.asarray(E_CATEGORIES))
_NU = np.asarray(NU_CATEGORIES)

# Pairs an annotator mixes up from appearance alone; symmetric.
DEFAULT_LOOKALIKES: tuple[tuple[str, str], ...] = (
    ("plastic", "rubber"),
    ("plastic", "ceramic"),
    ("wood", "leather"),
    ("ceramic", "stone"),
    ("glass", "jelly"),
    ("snow", "sand"),
    ("snow", "foam"),
    ("paper", "fabric"),
    ("plasticine", "rubber"),
    ("metal", "plastic"),
)


def e_class(E: float | np.ndarray) -> np.ndarray:
    """Index of the nearest E category in log10 space. E in Pa, must be positive."""
    logs = np.log10(np.asarray(E, dtype=np.float64))
    return np.abs(logs[..., None] - _LOG_E).argmin(-1)


def nu_class(nu: float | np.ndarray) -> np.ndarray:
    """Index of the nearest Poisson-ratio category."""
    return np.abs(np.asarray(nu, dtype=np.float64)[..., None] - _NU).argmin(-1)


@dataclass
class AnnotatorConfig:
    """Noise model of the automatic annotator (all probabilities per asset)."""

    p_neighbour_E: float = 0.2  # chance the E label moves one category up or down
    p_neighbour_nu: float = 0.2  # same for nu
    # Systematic bias in categories (+1 = one category stiffer), keyed by the *annotated* material,
    # because an annotator's numbers follow what it believes the material is.
    bias_E: dict[str, int] = field(
        default_factory=lambda: {"rubber": 1, "leather": 1, "fabric": -1, "snow": 1, "paper": -1}
    )
    bias_nu: dict[str, int] = field(default_factory=lambda: {"sand": -1, "foam": 1})
    p_material: float = 0.1  # chance the material is replaced by one of its look-alikes
    lookalikes: tuple[tuple[str, str], ...] = DEFAULT_LOOKALIKES

    def __post_init__(self) -> None:
        for name in ("p_neighbour_E", "p_neighbour_nu", "p_material"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"AnnotatorConfig.{name} must be a probability in [0, 1], got {value}")
        self.lookalikes = tuple(tuple(pair) for pair in self.lookalikes)  # JSON/YAML gives lists

    def partners(self, material: str) -> list[str]:
        """Look-alikes of ``material``, sorted so draws are reproducible."""
        out = {b for a, b in self.lookalikes if a == material} | {
            a for a, b in self.lookalikes if b == material
        }
        return sorted(out)

    @classmethod
    def from_dict(cls, d: dict) -> AnnotatorConfig:
        known = set(cls.__dataclass_fields__)
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown annotator settings {sorted(unknown)}; known: {sorted(known)}")
        return cls(**d)


@dataclass
class Annotation:
    """Labels of one asset as the annotator gives them."""

    material: str
    E_class: int  # index into E_CATEGORIES
    nu_class: int  # index into NU_CATEGORIES
    E_base: int  # class before the random neighbour move (true class + bias), kept for auditing
    nu_base: int

    @property
    def E(self) -> float:
        return E_CATEGORIES[self.E_class]

    @property
    def nu(self) -> float:
        return NU_CATEGORIES[self.nu_class]

    def to_json(self) -> dict:
        return {
            "material": self.material,
            "E": self.E,
            "nu": self.nu,
            "E_class": self.E_class,
            "nu_class": self.nu_class,
        }


def _move_to_neighbour(cls: int, n: int, u: float) -> int:
    # At the ends there is one neighbour, so the move always happens with the configured chance.
    if cls == 0:
        return 1
    if cls == n - 1:
        return n - 2
    return cls + (1 if u < 0.5 else -1)


def annotate(
    material: str, E: float, nu: float, rng: np.random.Generator, config: AnnotatorConfig
) -> Annotation:
    """Draw the annotator's labels for an asset with true ``material``, ``E`` (Pa) and ``nu``.

    Every random draw happens whatever the branch, so an asset's labels depend only on its rng.
    """
    if not (math.isfinite(E) and E > 0):
        raise ValueError(f"annotate: E must be a positive number of pascals, got {E}")
    u_mat, u_pick, u_e, u_nu, dir_e, dir_nu = rng.random(6)
    partners = config.partners(material)
    annotated = material
    if partners and u_mat < config.p_material:
        annotated = partners[int(u_pick * len(partners))]
    n_e, n_nu = len(E_CATEGORIES), len(NU_CATEGORIES)
    e_base = int(np.clip(int(e_class(E)) + config.bias_E.get(annotated, 0), 0, n_e - 1))
    nu_base = int(np.clip(int(nu_class(nu)) + config.bias_nu.get(annotated, 0), 0, n_nu - 1))
    e_lab = _move_to_neighbour(e_base, n_e, dir_e) if u_e < config.p_neighbour_E else e_base
    nu_lab = _move_to_neighbour(nu_base, n_nu, dir_nu) if u_nu < config.p_neighbour_nu else nu_base
    return Annotation(annotated, e_lab, nu_lab, e_base, nu_base)
