"""Boundary conditions: the ground plane and moving velocity boxes.

Where the ground acts (issue 24): a grid node's velocity reaches every particle within 1.5 cells
(quadratic B-splines), so a condition on the nodes at or below the plane (``contact="nodes"``,
``held_depth=0``; the default for sticky grounds) holds a body about a cell above it: impacts
begin while its surface is ~1.25 cells up and it rests a cell high. With ``held_depth=SURFACE_DEPTH`` the
nodes 7/8 cell or more below it are held, on a grid aligned so a node plane lies there
(``GridSpec.aligned``); held that deep, the nodes reach the lowest particles only through the
tails of their stencils, so a Coulomb ground also takes friction on the node layer above
(``surface_friction``), and the support is compliant: soft or heavy bodies sink by a load- and
stiffness-dependent depth.

``contact="particles"``, the default for slip and Coulomb grounds (``physgm.sim.mpm.particle_ground``),
acts on the particles instead: each particle whose material surface (half a particle spacing s
below it) is under the plane is pushed out by a penalty spring as stiff as a layer s thick of
its material's shear modulus G (stiffer for a body about as soft as its own weight), with a
normal dashpot (``damping`` = zeta 0.2), so impacts begin at the surface, bodies rest there
(their surface sinks rho g H s / X, X the spring's modulus: 0.07 cell for a 10 cm jelly cube at
E = 2e3 Pa), and an elastic ball keeps most of its bounce (restitution
0.909); slow approaches are damped on the grid against the weight each spring carries
(``rest_damping``), so a body resting on its springs stops rocking; the nodes two cells or more
below the plane stay held as a safety net that a resting body never reaches. Without the dashpot
the elastic contact kept a hard-hit jelly bouncing and moved two test observables out of their
bounds (docs/measurements_sim.md, section 11). Sticky
grounds stay on the nodes at the plane: no surface variant kept both a sand heap's slope and a
column collapse's run-out (section 7).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import warp as wp

from physgm.sim.mpm.grid import GridSpec

GROUND_SEPARATE = wp.constant(0)  # Coulomb friction, may lift off
GROUND_SLIP = wp.constant(1)  # frictionless, may lift off
GROUND_STICKY = wp.constant(2)  # nodes below the plane are fixed
_GROUND_MODES = {"separate": 0, "slip": 1, "sticky": 2}
# ``GroundPlane.held_depth`` that puts contact at the surface (module docstring), cells.
SURFACE_DEPTH = 0.875
# With contact on the particles, the nodes this many cells or more below the plane are held too: a
# safety net that a resting body's stencils (1.5 cells below its lowest particles) never reach.
NET_DEPTH = 2.0
_CONTACTS = ("particles", "nodes")
# Largest zeta of the particle contact's dashpot: its force 4 zeta m |v_n| / tau reaches the cap
# m |v_n| / tau there (particle_ground).
MAX_DAMPING = 0.25


@wp.struct
class GroundStruct:
    enabled: int
    height: float  # plane z = height, m
    friction: float  # Coulomb coefficient
    mode: int  # GROUND_SEPARATE / GROUND_SLIP / GROUND_STICKY
    depth: float  # held_depth, cells
    particles: int  # 1: penalty contact on the particles (particle_ground), nodes held from NET_DEPTH down
    damping: float  # zeta of the particle contact's normal dashpot (particle_ground)
    rest_damping: float  # zeta of its resting dashpot on the grid (particle_ground)
    rest_speed: float  # m/s, approaches slower than this are damped on the grid (0: never)
    inv_gravity: float  # s^2/m, 1 / |g| of the scene (0 without gravity)
    friction_rate: float  # 1 / cfl of the solver: the particle friction's cap (particle_ground)


@wp.struct
class BoxStruct:
    lo: wp.vec3  # box corner at t = start, m
    hi: wp.vec3
    velocity: wp.vec3  # m/s, imposed on the nodes inside and moving the box
    start: float  # s
    stop: float  # s
    hold: int  # 1: after stop the box stays and fixes its nodes; 0: it is released
    fixed: wp.vec3  # 1 for each velocity component the box prescribes, 0 for one it leaves free
    carry: int  # 1: the particles inside move with the box too; 0: only its nodes are held


@dataclass(frozen=True)
class GroundPlane:
    """Plane z = ``height`` acting on the particles (default) or on the grid nodes (module docstring).

    mode: "separate" (Coulomb friction ``friction``, lift-off allowed), "slip" (frictionless,
    lift-off allowed) or "sticky" (held nodes do not move).
    contact: "particles" (slip and Coulomb grounds, held_depth 0: a penalty spring on each
    particle's material surface, ``particle_ground``; contact and rest at the plane) or "nodes"
    (the grid condition); None (default) picks "particles" unless the ground is sticky or held
    at depth.
    stiffness: kappa of the particle contact: a particle of spacing s gets min(max(kappa G,
    min(8 W, M (2 s / dx)^2)), M) s N/m, G and M its material's shear and P-wave moduli, W the
    pressure under the body's weight, dx the cell (``particle_ground``).
    damping: zeta of the particle contact's normal dashpot, c = 2 zeta sqrt(k m), in [0, 0.25]
    (``particle_ground``); 0 makes the contact elastic.
    rest_damping: zeta of the resting dashpot, c = 2 zeta sqrt(k W / g) with W the weight the
    spring carries, applied on the grid to approaches slower than a fall through half a particle
    spacing (``particle_ground``); 0 turns it off.
    held_depth: nodes contact only: 0 holds the nodes at or below the plane (contact starts ~1.25
    cells up, bodies rest a cell high); ``SURFACE_DEPTH`` puts contact and the rest of light bodies
    at the plane but lets soft or heavy bodies sink (module docstring).
    contact_height: the plane the particle contact pushes from, m; None (default): the ground's
    height, lowered under a body that starts in it (``particle_ground.contact_plane``). A solver
    rebuilt in the middle of a run is given its predecessor's, so a body resting on its springs
    is not lowered again.
    """

    height: float = 0.0
    friction: float = 0.3
    mode: str = "separate"
    held_depth: float = 0.0  # cells, nodes contact; SURFACE_DEPTH: contact at the surface
    contact: str | None = None  # None: "particles" unless sticky or held_depth > 0, then "nodes"
    stiffness: float = 1.0  # kappa of the particle contact (particle_ground)
    damping: float = 0.2  # zeta of the particle contact's normal dashpot (particle_ground)
    rest_damping: float = 0.5  # zeta of its resting dashpot on the grid (particle_ground)
    contact_height: float | None = None  # m, the particle contact's plane; None: from the start

    def __post_init__(self) -> None:
        if self.contact is None:
            nodes = self.mode == "sticky" or self.held_depth > 0
            object.__setattr__(self, "contact", "nodes" if nodes else "particles")
        if self.mode not in _GROUND_MODES:
            raise ValueError(f"ground mode {self.mode!r} unknown; use one of {', '.join(_GROUND_MODES)}")
        if not (math.isfinite(self.friction) and self.friction >= 0.0):
            raise ValueError(f"ground friction={self.friction!r} must be finite and >= 0")
        if not (math.isfinite(self.held_depth) and 0.0 <= self.held_depth < 1.5):
            raise ValueError(
                f"ground held_depth={self.held_depth!r} cells must be in [0, 1.5); try 0 or 0.875"
            )
        if not (math.isfinite(self.stiffness) and self.stiffness > 0.0):
            raise ValueError(f"ground stiffness={self.stiffness!r} must be finite and > 0; try 1")
        if not (math.isfinite(self.damping) and 0.0 <= self.damping <= MAX_DAMPING):
            raise ValueError(
                f"ground damping={self.damping!r} must be in [0, {MAX_DAMPING}] (the dashpot is capped "
                "at the spring's period there); try 0"
            )
        if not (math.isfinite(self.rest_damping) and self.rest_damping >= 0.0):
            raise ValueError(f"ground rest_damping={self.rest_damping!r} must be finite and >= 0; try 0.5")
        if self.contact_height is not None and not (
            math.isfinite(self.contact_height) and self.contact_height <= self.height
        ):
            raise ValueError(
                f"ground contact_height={self.contact_height!r} must be finite and at most the ground's "
                f"height {self.height} (the contact plane is only ever lowered); leave it None"
            )
        if self.contact not in _CONTACTS:
            raise ValueError(f"ground contact {self.contact!r} unknown; use one of {', '.join(_CONTACTS)}")
        if self.contact == "particles" and (self.mode == "sticky" or self.held_depth > 0):
            raise ValueError(
                f"a {self.mode} ground with held_depth={self.held_depth} acts on the grid nodes; "
                "use contact='nodes' (particle contact is for slip and Coulomb grounds, held_depth 0)"
            )

    @property
    def on_particles(self) -> bool:
        """Penalty contact on the particles (``particle_ground``)."""
        return self.contact == "particles"

    def on_nodes(self) -> GroundPlane:
        """This ground with the grid condition at the plane (for steps that replace the scatter's
        forces, such as the implicit solve)."""
        return replace(self, contact="nodes") if self.on_particles else self

    def surface_friction_layer(self, grid: GridSpec) -> int | None:
        """k of the top held node layer of ``grid``, whose layer above takes the friction at the
        surface (``surface_friction``), or None: only a Coulomb ground held at depth has one."""
        if self.held_depth <= 0 or self.mode != "separate":
            return None
        layer = round((self.height - self.held_depth * grid.dx - grid.origin[2]) / grid.dx)
        return layer if 0 <= layer < grid.res[2] - 1 else None

    def pack(self) -> GroundStruct:
        s = GroundStruct()
        s.enabled = 1
        s.height = float(self.height)
        s.friction = float(self.friction)
        s.mode = _GROUND_MODES[self.mode]
        s.depth = float(self.held_depth)
        s.particles = int(self.on_particles)
        s.damping = float(self.damping)
        s.rest_damping = float(self.rest_damping)
        s.rest_speed = 0.0  # the particle contact's are set by particle_ground.pack_contact
        s.inv_gravity = 0.0
        s.friction_rate = 1.0
        return s


@dataclass(frozen=True)
class VelocityBox:
    """Grid nodes inside [lo, hi] (moving with ``velocity`` from ``start`` to ``stop``) take that velocity.

    Grips of a stretch test are two boxes moving apart; a clamp is a box with zero velocity.
    After ``stop`` a held box stays where it ended and fixes its nodes (velocity 0). ``axes``
    names the velocity components the box prescribes; the others stay free, so a grip that
    prescribes only the pulling axis lets the held end narrow as the body stretches (a slip grip:
    the ends of a tensile test on rollers, which leaves a bar in uniform uniaxial tension).
    With ``carry`` the particles inside move with the box as well, so none creeps out of a clamp;
    without it they follow the held nodes, and the body's strain runs smoothly into the grip
    instead of tearing at its edge (carried particles keep their spacing while the first free
    layer is pulled away from them).
    """

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    start: float = 0.0
    stop: float = math.inf
    hold: bool = True
    axes: tuple[bool, bool, bool] = (True, True, True)
    carry: bool = True

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.lo, float), np.asarray(self.hi, float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(lo < hi):
            raise ValueError(f"velocity box needs lo < hi componentwise, got lo={self.lo}, hi={self.hi}")
        vel = np.asarray(self.velocity, float)
        if vel.shape != (3,) or not np.isfinite(vel).all():
            raise ValueError(f"velocity box velocity must be three finite numbers, got {self.velocity}")
        for name, value in (("lo", lo), ("hi", hi), ("velocity", vel)):
            object.__setattr__(self, name, tuple(float(c) for c in value))
        axes = tuple(self.axes)
        if len(axes) != 3 or not all(isinstance(a, (bool, np.bool_)) for a in axes) or not any(axes):
            raise ValueError(f"velocity box axes must be three booleans, at least one True, got {self.axes}")
        if any(not a and c != 0.0 for a, c in zip(axes, vel, strict=True)):
            raise ValueError(
                f"velocity box moves along an axis it leaves free: velocity {self.velocity}, axes {axes}"
            )
        object.__setattr__(self, "axes", tuple(bool(a) for a in axes))

    def pack(self) -> BoxStruct:
        s = BoxStruct()
        s.lo = wp.vec3(*self.lo)
        s.hi = wp.vec3(*self.hi)
        s.velocity = wp.vec3(*self.velocity)
        s.start = float(self.start)
        s.stop = float(min(self.stop, 1.0e30))
        s.hold = int(self.hold)
        s.fixed = wp.vec3(*(1.0 if a else 0.0 for a in self.axes))
        s.carry = int(self.carry)
        return s


def no_ground() -> GroundStruct:
    s = GroundStruct()
    s.enabled = 0
    s.particles = 0
    s.damping = 0.0
    s.rest_damping = 0.0
    s.rest_speed = 0.0
    s.inv_gravity = 0.0
    s.friction_rate = 1.0
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
    target = wp.vec3(0.0)
    if moving:
        target = box.velocity
    # A select, not v + fixed (target - v): a held component is then the target to the bit.
    f = box.fixed
    return wp.vec3(
        wp.where(f[0] > 0.0, target[0], v[0]),
        wp.where(f[1] > 0.0, target[1], v[1]),
        wp.where(f[2] > 0.0, target[2], v[2]),
    )


@wp.func
def ground_velocity(ground: GroundStruct, pos: wp.vec3, dx: float, v: wp.vec3) -> wp.vec3:
    """Velocity of a node at ``pos`` after the ground plane acted on ``v``.

    With ``held_depth`` 0 the nodes at or below the plane are held; otherwise the nodes from
    ``held_depth`` cells below it down, tested half a cell above that node plane so that
    rounding on the aligned grid cannot matter; with contact on the particles, the safety net
    from NET_DEPTH cells down (module docstring).
    """
    limit = ground.height
    if ground.particles != 0:
        limit = ground.height - NET_DEPTH * dx
    elif ground.depth > 0.0:
        limit = ground.height - (ground.depth - 0.5) * dx
    if ground.enabled == 0 or pos[2] > limit:
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


@wp.func
def ground_grip(ground: GroundStruct, m: float, v_free: wp.vec3, vel: wp.vec3) -> float:
    """Friction impulse a held node of mass ``m`` leaves for the surface layer above it, N s.

    Coulomb grounds held at depth only (``surface_friction``): what its normal impulse allows, less
    what its own sliding used; 0 otherwise.
    """
    if ground.mode != GROUND_SEPARATE or ground.depth <= 0.0:
        return 0.0
    normal = m * (vel[2] - v_free[2])
    used = m * wp.length(wp.vec3(vel[0] - v_free[0], vel[1] - v_free[1], 0.0))
    return wp.max(ground.friction * normal - used, 0.0)
