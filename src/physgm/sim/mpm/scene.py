"""``Scene``: what the solver needs besides particles, materials and grid.

Gravity, the ground plane and velocity boxes (``boundary.py``), side walls and periodic axes
(``walls.py``) and a drag. The registry of scene drivers that build one for an object from
conf/sim/scene/<name>.yaml is ``physgm.sim.scenes``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from physgm.sim.mpm.boundary import GroundPlane, VelocityBox
from physgm.sim.mpm.walls import PeriodicAxis, SideWall


@dataclass(frozen=True)
class Scene:
    """Everything the solver needs besides particles, materials and grid."""

    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)  # m/s^2
    ground: GroundPlane | None = None
    boxes: tuple[VelocityBox, ...] = field(default_factory=tuple)
    damping: float = 0.0  # 1/s, mass-proportional drag on grid velocities (0: none)
    walls: tuple[SideWall, ...] = field(default_factory=tuple)  # side walls (walls.py)
    periodic: tuple[PeriodicAxis, ...] = field(default_factory=tuple)  # periodic axes (walls.py)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.damping) and self.damping >= 0.0):
            raise ValueError(f"scene damping={self.damping!r} 1/s must be finite and >= 0")
        g = np.asarray(self.gravity, dtype=np.float64)
        if g.shape != (3,) or not np.isfinite(g).all():
            raise ValueError(f"gravity={self.gravity!r} must be three finite numbers (m/s^2)")
        object.__setattr__(self, "gravity", tuple(float(c) for c in g))
        object.__setattr__(self, "boxes", tuple(self.boxes))
        object.__setattr__(self, "walls", tuple(self.walls))
        object.__setattr__(self, "periodic", tuple(self.periodic))

    def with_ground_on_nodes(self) -> Scene:
        """This scene with its ground's grid condition at the plane instead of particle contact
        (``GroundPlane.on_nodes``), for steps whose solve replaces the scatter's forces."""
        return self if self.ground is None else replace(self, ground=self.ground.on_nodes())

    @property
    def grid_free(self) -> bool:
        """Nothing here is tied to the grid's place or the solver's clock, so a run may continue on
        a rebuilt solver elsewhere (after a closed-form flight, on a grid moved under the body):
        velocity boxes keep a schedule a rebuilt solver would restart; side walls and periodic axes
        are the grid's."""
        return not (self.boxes or self.walls or self.periodic)
