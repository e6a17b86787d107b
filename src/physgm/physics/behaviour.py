"""What a viewer of the clip sees a material do: its behaviour class.

Confusing ceramic with metal changes little in a clip (both fall as rigid bodies); confusing
ceramic with jelly changes everything. Evaluation therefore scores the behaviour class next to
the material (``physgm.metrics.physics_metrics``). The classes follow how the simulator treats each
material: the planner runs the stiff ones as rigid bodies, the elastic ones spring back, the
von Mises ones keep a dent, the Drucker-Prager ones flow as grains, and foam crushes.
"""

from __future__ import annotations

import torch
from torch import Tensor

from physgm.physics.materials import MATERIAL_NAMES

BEHAVIOURS: tuple[str, ...] = ("rigid", "soft elastic", "plastic", "granular", "fluid", "foam")

# behaviour class -> its materials; every name of MATERIAL_NAMES exactly once (checked on import)
_MATERIALS_OF: dict[str, tuple[str, ...]] = {
    # stiff enough that a drop or push leaves no visible deformation: rigid bodies
    "rigid": ("plastic", "wood", "metal", "ceramic", "stone", "paper", "glass"),
    # deform visibly and spring back
    "soft elastic": ("rubber", "jelly", "fabric", "leather"),
    # keep their deformation (von Mises plasticity at a low yield stress)
    "plastic": ("plasticine",),
    # flow as grains (Drucker-Prager)
    "granular": ("sand", "snow"),
    # crush and partly recover
    "foam": ("foam",),
}
MATERIAL_BEHAVIOUR: dict[str, str] = {m: b for b, names in _MATERIALS_OF.items() for m in names}

if (
    sum(map(len, _MATERIALS_OF.values())) != len(MATERIAL_NAMES)
    or set(MATERIAL_BEHAVIOUR) != set(MATERIAL_NAMES)
    or not set(MATERIAL_BEHAVIOUR.values()) <= set(BEHAVIOURS)
):
    raise ValueError("MATERIAL_BEHAVIOUR must give every material of MATERIAL_NAMES one class of BEHAVIOURS")


def behaviour_index() -> Tensor:  # [M] int64: behaviour class of each material index
    """Behaviour class index of every material, in ``MATERIAL_NAMES`` order."""
    return torch.tensor([BEHAVIOURS.index(MATERIAL_BEHAVIOUR[m]) for m in MATERIAL_NAMES])


def behaviour_of(material: int | str) -> str:
    name = MATERIAL_NAMES[material] if isinstance(material, int) else material
    return MATERIAL_BEHAVIOUR[name]
