"""Boundary conditions acting on the grid: ground plane and moving velocity boxes.

Where the ground acts (issue 24): a grid node's velocity reaches every particle within 1.5 cells
(quadratic B-splines), and a particle feels a node firmly once it is within about a cell. A
condition on the nodes at the plane therefore held a body about a cell above it: impacts began
while the surface was ~1.25 cells up and bodies rested a cell high. The ground now acts on the
nodes ``HELD_DEPTH`` cells or more below the plane, and the solver aligns its grid so that a node
plane lies exactly there (``GridSpec.aligned``): a particle meets the condition once the
material's surface (half a particle spacing, a quarter cell, below the lowest particles) reaches
the plane, and a body rests with its lowest particles within a quarter cell of it. At one cell
down a stiff block rested at +0.05 cells and a soft jelly (E = 1e4 Pa, 10-20 % strain at its
base) sank to -0.3 cells; 7/8 of a cell puts both inside +-0.2 (docs/measurements_sim.md).
An earlier attempt that also clamped particles to the plane lost restitution; shifting where the
nodes are held alone keeps the contact as elastic as before (ball restitution 0.946 -> 0.940).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

GROUND_SEPARATE = wp.constant(0)  # Coulomb friction, may lift off
GROUND_SLIP = wp.constant(1)  # frictionless, may lift off
GROUND_STICKY = wp.constant(2)  # nodes below the plane are fixed
_GROUND_MODES = {"separate": 0, "slip": 1, "sticky": 2}
# Depth below the plane of the highest held node plane, cells (module docstring).
HELD_DEPTH = 0.875
_HELD_DEPTH = wp.constant(HELD_DEPTH)


@wp.struct
class GroundStruct:
    enabled: int
    height: float  # plane z = height, m
    friction: float  # Coulomb coefficient
    mode: int  # GROUND_SEPARATE / GROUND_SLIP / GROUND_STICKY


@wp.struct
class BoxStruct:
    lo: wp.vec3  # box corner at t = start, m
    hi: wp.vec3
    velocity: wp.vec3  # m/s, imposed on the nodes inside and moving the box
    start: float  # s
    stop: float  # s
    hold: int  # 1: after stop the box stays and fixes its nodes; 0: it is released


@dataclass(frozen=True)
class GroundPlane:
    """Plane z = ``height`` acting on the grid nodes ``HELD_DEPTH`` cells or more below it (module docstring).

    mode: "separate" (Coulomb friction ``friction``, lift-off allowed), "slip" (frictionless,
    lift-off allowed) or "sticky" (nodes below the plane do not move).
    """

    height: float = 0.0
    friction: float = 0.3
    mode: str = "separate"

    def __post_init__(self) -> None:
        if self.mode not in _GROUND_MODES:
            raise ValueError(f"ground mode {self.mode!r} unknown; use one of {', '.join(_GROUND_MODES)}")
        if not (math.isfinite(self.friction) and self.friction >= 0.0):
            raise ValueError(f"ground friction={self.friction!r} must be finite and >= 0")

    def pack(self) -> GroundStruct:
        s = GroundStruct()
        s.enabled = 1
        s.height = float(self.height)
        s.friction = float(self.friction)
        s.mode = _GROUND_MODES[self.mode]
        return s


@dataclass(frozen=True)
class VelocityBox:
    """Grid nodes inside [lo, hi] (moving with ``velocity`` from ``start`` to ``stop``) take that velocity.

    Grips of a stretch test are two boxes moving apart; a clamp is a box with zero velocity.
    After ``stop`` a held box stays where it ended and fixes its nodes (velocity 0).
    """

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    start: float = 0.0
    stop: float = math.inf
    hold: bool = True

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.lo, float), np.asarray(self.hi, float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(lo < hi):
            raise ValueError(f"velocity box needs lo < hi componentwise, got lo={self.lo}, hi={self.hi}")
        vel = np.asarray(self.velocity, float)
        if vel.shape != (3,) or not np.isfinite(vel).all():
            raise ValueError(f"velocity box velocity must be three finite numbers, got {self.velocity}")
        for name, value in (("lo", lo), ("hi", hi), ("velocity", vel)):
            object.__setattr__(self, name, tuple(float(c) for c in value))

    def pack(self) -> BoxStruct:
        s = BoxStruct()
        s.lo = wp.vec3(*self.lo)
        s.hi = wp.vec3(*self.hi)
        s.velocity = wp.vec3(*self.velocity)
        s.start = float(self.start)
        s.stop = float(min(self.stop, 1.0e30))
        s.hold = int(self.hold)
        return s


def no_ground() -> GroundStruct:
    s = GroundStruct()
    s.enabled = 0
    return s


@wp.func
def box_velocity(box: BoxStruct, pos: wp.vec3, t: float, v: wp.vec3) -> wp.vec3:
    """Velocity of a node at ``pos`` after box ``box`` acted on velocity ``v``."""
    if t < box.start:
        return v
    moving = t < box.stop
    if not moving and box.hold == 0:
        return v
    shift = box.velocity * (wp.min(t, box.stop) - box.start)
    lo = box.lo + shift
    hi = box.hi + shift
    if pos[0] < lo[0] or pos[1] < lo[1] or pos[2] < lo[2]:
        return v
    if pos[0] > hi[0] or pos[1] > hi[1] or pos[2] > hi[2]:
        return v
    if moving:
        return box.velocity
    return wp.vec3(0.0)


@wp.func
def ground_velocity(ground: GroundStruct, pos: wp.vec3, dx: float, v: wp.vec3) -> wp.vec3:
    """Velocity of a node at ``pos`` after the ground plane acted on ``v``.

    Nodes from ``HELD_DEPTH`` cells below the plane down are held (module docstring); testing
    half a cell above that node plane makes the test robust to rounding on an aligned grid.
    """
    if ground.enabled == 0 or pos[2] > ground.height - (_HELD_DEPTH - 0.5) * dx:
        return v
    if ground.mode == GROUND_STICKY:
        return wp.vec3(0.0)
    vn = v[2]
    if vn >= 0.0:
        return v  # separating: leaving the ground is free
    vt = wp.vec3(v[0], v[1], 0.0)
    if ground.mode == GROUND_SLIP:
        return vt
    vt_norm = wp.length(vt)
    if vt_norm <= -ground.friction * vn:
        return wp.vec3(0.0)
    return vt * (1.0 + ground.friction * vn / vt_norm)
