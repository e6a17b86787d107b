"""The material table: one YAML per material under conf/sim/material/, loaded into a registry.

The YAML files ship inside the package (``physgm.resources``), so an installed wheel reads the
same table as the checkout.

``MATERIAL_NAMES`` fixes the class order of the model's material head (15 classes). Each entry
names its constitutive model (``physgm.sim.constitutive.MODELS``), density, default E and nu,
the typical E and nu ranges, the plasticity extras of its model and a ``source`` for every
value. ``get_material(name)`` returns a validated ``Material``; ``Material.params(E, nu)`` the
solver parameters.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from functools import cache
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any

import yaml

from physgm.resources import package_file

MATERIAL_NAMES: tuple[str, ...] = (
    "plastic",
    "wood",
    "metal",
    "fabric",
    "ceramic",
    "stone",
    "paper",
    "leather",
    "glass",
    "rubber",
    "foam",
    "snow",
    "sand",
    "jelly",
    "plasticine",
)

MATERIAL_DIR = package_file("conf", "sim", "material")
PLASTICITY_KEYS = ("yield_stress", "hardening", "friction_angle", "cohesion", "viscosity")


@dataclass(frozen=True)
class Material:
    """One row of the material table (SI units)."""

    name: str
    model: str  # constitutive model name in physgm.sim.constitutive.MODELS
    density: float  # kg/m^3
    E: float  # default Young's modulus, Pa
    nu: float  # default Poisson ratio
    E_range: tuple[float, float]  # typical Young's moduli, Pa
    nu_range: tuple[float, float]  # typical Poisson ratios
    plasticity: dict[str, float] = field(default_factory=dict)  # model extras (yield_stress, ...)
    source: dict[str, str] = field(default_factory=dict)  # value name -> citation
    # Tensile strain past which the model stops describing the real material: it breaks there
    # (fracture is not modelled), or, under a model without plasticity, it yields. None: none given
    # (rubber, gels and foams stretch to twice their length; fabrics and leathers range too widely
    # for one value; the granular models and plasticine give way within the model).
    tensile_limit: float | None = None

    @property
    def index(self) -> int:
        """Class index of this material in ``MATERIAL_NAMES``."""
        return MATERIAL_NAMES.index(self.name)

    def params(self, E: float | None = None, nu: float | None = None):
        """Solver parameters (``physgm.sim.constitutive.MaterialParams``) at this or another E / nu."""
        # Imported here so that reading the table does not load Warp.
        from physgm.sim.constitutive import MaterialParams

        return MaterialParams(
            model=self.model,
            E=float(self.E if E is None else E),
            nu=float(self.nu if nu is None else nu),
            density=float(self.density),
            **{k: float(v) for k, v in self.plasticity.items()},
        )


@dataclass(frozen=True)
class PhysicsSpec:
    """The physics one simulation runs with: a material of the table at a chosen E and nu (SI units).

    The constitutive model and its plasticity parameters come from the material's row
    (``params``); E, nu and density left at None take the row's values too.
    """

    material: str  # a name in the material table
    E: float | None = None  # Young's modulus, Pa
    nu: float | None = None  # Poisson ratio
    density: float | None = None  # kg/m^3
    restitution: float | None = None  # ground restitution of the rigid path; None: the planner's

    def __post_init__(self) -> None:
        get_material(self.material)  # an unknown name stops here, with the table's names
        if self.E is not None and not (math.isfinite(self.E) and self.E > 0):
            raise ValueError(f"E={self.E!r} Pa must be finite and > 0")
        if self.nu is not None and not (math.isfinite(self.nu) and 0 <= self.nu < 0.5):
            raise ValueError(f"nu={self.nu!r} must be in [0, 0.5)")
        if self.density is not None and not (math.isfinite(self.density) and self.density > 0):
            raise ValueError(f"density={self.density!r} kg/m^3 must be finite and > 0")

    @classmethod
    def from_dict(cls, physics: Mapping[str, Any]) -> PhysicsSpec:
        """From a JSON-shaped description (physical.json); unknown keys are errors."""
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(physics) - set(names))
        if unknown or "material" not in physics:
            raise ValueError(
                f"a physics description needs 'material' and takes only {names}; got {dict(physics)!r}"
            )
        return cls(
            **{
                k: (str(v) if k == "material" else None if v is None else float(v))
                for k, v in physics.items()
            }
        )

    def to_dict(self) -> dict[str, Any]:
        """The JSON-shaped description ``from_dict`` reads, fields left at None omitted."""
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}

    def params(self):
        """Solver parameters (``physgm.sim.constitutive.MaterialParams``) of this physics."""
        params = get_material(self.material).params(E=self.E, nu=self.nu)
        return params if self.density is None else replace(params, density=float(self.density))


def _fail(path: Path | Traversable, message: str) -> None:
    raise ValueError(f"material file {path}: {message}")


def _validate(m: Material, path: Path | Traversable) -> None:
    from physgm.sim.constitutive import MODELS

    if m.model not in MODELS:
        _fail(path, f"unknown constitutive model {m.model!r}; known models: {', '.join(MODELS)}")
    if not (math.isfinite(m.density) and m.density > 0):
        _fail(path, f"density={m.density!r} kg/m^3 must be > 0")
    lo, hi = m.E_range
    if not (0 < lo <= m.E <= hi and math.isfinite(hi)):
        _fail(path, f"need 0 < E_range[0] <= E <= E_range[1], got E={m.E!r}, E_range={m.E_range!r}")
    nlo, nhi = m.nu_range
    if not (-1 < nlo <= m.nu <= nhi < 0.5):
        _fail(
            path,
            f"need -1 < nu_range[0] <= nu <= nu_range[1] < 0.5, got nu={m.nu!r}, nu_range={m.nu_range!r}",
        )
    unknown = set(m.plasticity) - set(PLASTICITY_KEYS)
    if unknown:
        _fail(path, f"unknown plasticity keys {sorted(unknown)}; allowed: {', '.join(PLASTICITY_KEYS)}")
    if m.tensile_limit is not None and not (math.isfinite(m.tensile_limit) and m.tensile_limit > 0):
        _fail(path, f"tensile_limit={m.tensile_limit!r} must be a positive strain (or absent)")
    limit = () if m.tensile_limit is None else ("tensile_limit",)
    missing = [k for k in ("E", "nu", "density", *m.plasticity, *limit) if not m.source.get(k)]
    if missing:
        _fail(path, f"no source given for {missing}; every value needs a `source:` entry")
    m.params()  # the solver's own validation (e.g. yield stress > 0 for von Mises)


def load_material(path: Path | Traversable) -> Material:
    """Read and validate one material YAML file (a path, or a file inside the package)."""
    raw = yaml.safe_load(path.read_text())
    required = ("name", "model", "density", "E", "nu", "E_range", "nu_range", "source")
    absent = [k for k in required if k not in raw]
    if absent:
        _fail(path, f"missing keys {absent}")
    material = Material(
        name=str(raw["name"]),
        model=str(raw["model"]),
        density=float(raw["density"]),
        E=float(raw["E"]),
        nu=float(raw["nu"]),
        E_range=tuple(float(v) for v in raw["E_range"]),
        nu_range=tuple(float(v) for v in raw["nu_range"]),
        plasticity={str(k): float(v) for k, v in (raw.get("plasticity") or {}).items()},
        source={str(k): str(v) for k, v in raw["source"].items()},
        tensile_limit=None if raw.get("tensile_limit") is None else float(raw["tensile_limit"]),
    )
    stem = path.name.removesuffix(".yaml")
    if material.name != stem:
        _fail(path, f"name {material.name!r} must match the file name {stem!r}")
    _validate(material, path)
    return material


@cache
def material_table() -> dict[str, Material]:
    """All materials, in ``MATERIAL_NAMES`` order."""
    if not MATERIAL_DIR.is_dir():
        raise FileNotFoundError(
            f"material table directory {MATERIAL_DIR} not found (conf/sim/material/*.yaml)"
        )
    table = {}
    for name in MATERIAL_NAMES:
        path = MATERIAL_DIR / f"{name}.yaml"
        if not path.is_file():
            raise FileNotFoundError(f"material {name!r} has no file {path}")
        table[name] = load_material(path)
    return table


def get_material(name: str) -> Material:
    """The material called ``name``; raises ValueError listing the known names otherwise."""
    table = material_table()
    if name not in table:
        raise ValueError(f"unknown material {name!r}; known materials: {', '.join(MATERIAL_NAMES)}")
    return table[name]


def log10_E_range(material: int | str) -> tuple[float, float]:
    """The table's E range of a material (its index in ``MATERIAL_NAMES`` or its name), log10 Pa."""
    lo, hi = get_material(MATERIAL_NAMES[material] if isinstance(material, int) else material).E_range
    return math.log10(lo), math.log10(hi)
