"""Ground contact on the particles: a damped penalty spring at each particle's surface.

``GroundPlane(contact="particles")``, the default for slip and Coulomb grounds (``boundary``).

A grid condition reaches a body through 1.5-cell stencils, so it acts a cell early (``boundary``).
Here the ground pushes the particles themselves: a particle of spacing s = V0^(1/3) (its rest
volume's side) carries the material down to s / 2 below its centre, and when that surface is a
depth d under the plane it gets the normal force

    f_n = k d,   k = X s   (N/m),   X = min(max(kappa G, min(LOAD_FACTOR W, M (2 s / dx)^2)), M),

G the shear modulus of its material (a fluid, which has none: its bulk modulus), M = lam + 2 mu
its P-wave modulus, kappa = ``GroundPlane.stiffness`` (1), W = rho |g| V^(1/3) the pressure at the
base of a compact body of the material's rest volume V, dx the grid's cell (``raised_modulus``).
Per particle column of cross-section s^2 the ground is as stiff as a layer s thick of a material
of modulus X: a body of height H rests with its surface rho g H s / X under the plane (0.013 dx for
the 5 cm test block; docs/measurements_sim.md section 11), and, the spring being elastic and its
dashpot light, an elastic body keeps most of its bounce. G, not M, where the body's weight allows:
the bulk cap (issue 25) lowers M and keeps G, so the ground does not sink a capped body deeper than
the uncapped one (except where the load term reaches the capped M); and a spring as stiff as M
made the bouncing ball's bottom layer chatter (restitution 0.908 against 0.938 with G).

The load term is for bodies about as soft as their own weight, a jelly of a few kPa: with G alone
a 10 cm cube at E = 2e3 Pa rested with its surface 1.15 spacings under the plane, and thrown down
at 3 m/s it went 3.7 spacings in; raised to LOAD_FACTOR W, 0.14 and 1.2 (section 40). It stops at
M (2 s / dx)^2, where the spring rings as fast as the material's P-wave crosses a cell (last
paragraph), so it never shortens the step: at 2 particles a cell axis that is M itself; a grid
the planner coarsened under the same particles (a push, dx = 2.6 s) affords 0.58 M.

On a Coulomb ground a tangential force opposes the particle's sliding velocity v_t, at most mu f_n
and at most m |v_t| / (cfl tau), tau = 2 / omega below. The solver's step never exceeds cfl tau
(last paragraph), so this is the strongest viscous friction that never reverses the motion within
a sub-step: a slow particle stops within about one sub-step, as close to sticking as an explicit
force comes. (With m |v_t| / tau instead, a plasticine lump that had landed kept turning and
sliding a few um a frame to the end of a 2 s clip; docs/measurements_sim.md section 17.) The
cap uses tau, not the sub-step dt, because the scatter runs before the next sub-step's dt is known
(``kernels``: the fused scatter must not depend on dt).

A normal dashpot takes energy at impact, as real contacts do (the conservative spring alone kept
a jelly hit at twice its wave speed bouncing): f_n = max(k d - c v_n, 0), c = 2 zeta sqrt(k m) =
4 zeta m / tau, zeta = ``GroundPlane.damping`` (0.2), so the ground never pulls. At the largest
zeta, 0.25, c v_n reaches m |v_n| / tau, so (dt <= cfl tau <= tau) the dashpot never reverses
the normal velocity within a sub-step. It acts on the bottom layer only and keeps most
of an elastic ball's bounce (restitution 0.938 elastic, 0.914 at 0.2; docs/measurements_sim.md
section 11).

A resting body rocks on its springs: each spring carries the column above it, so for the body's
slow modes the dashpot above, sized by the particle's own mass, is a damping ratio of about
zeta sqrt(m / m_column) (~0.05 for a 15-particle column), and a plasticine lump kept rocking
through a 2 s clip (docs/measurements_sim.md, sections 15-17). The resting dashpot damps those
modes without touching impacts: each particle also scatters c_r = 2 zeta_r sqrt(k W / g), W = k d
the weight its spring carries (at least m g), zeta_r = ``GroundPlane.rest_damping`` (0.5), into
the accumulators' spare component, and grid_update applies the sum c to a node whose velocity
approaches the ground slower than ``rest_speed`` = sqrt(|g| s), a fall through half a spacing:
v_z <- v_z m / (m + c dt), implicit, so stable at any c, and it only pushes. Impacts come in
faster than that and keep their bounce (the test ball's restitution: 0.909 with it, 0.914
without; docs/measurements_sim.md section 17); a resting body's motions are slower. Its impulse
joins the ground impulse.

The force enters the scatter like the stress force (``kernels.scatter_particle``), so it reaches
the grid as gravity does; ``pending`` sums what the particles got, and the next grid_update
adds it times that step's dt to the ground impulse (``kernels.WORK_GROUND``), which the
observables report as the ground's force.

Stability: alone on its mass m = rho s^3 the spring rings at omega = sqrt(k / m) = c_X / s, c_X =
sqrt(X / rho) <= c_p. The solver's step dt = cfl dx / c is taken with c >= c_X dx / (2 s)
(``contact_wave_speed``), so omega dt <= 2 cfl = 0.8 at the default cfl (and dt <= cfl tau <=
tau, as cfl <= 1), under the explicit limit 2. With 2 particles per cell axis (s = dx / 2) that
c is at most the material's own c_p, so the step does not change.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import warp as wp

from physgm.sim.constitutive import MODELS, MaterialParams
from physgm.sim.mpm.boundary import GROUND_SLIP, GroundPlane, GroundStruct

wp.set_module_options({"enable_backward": False})

# The spring is at least this many times the pressure under the body's own weight (``raised_modulus``),
# so a resting body's surface sinks at most 1 / LOAD_FACTOR of a spacing while the step affords it.
LOAD_FACTOR = 8.0


@wp.func
def touches_ground(particles: int, height: float, z: float, vol0: float) -> bool:
    """Is this particle's surface (s / 2 below it, s = vol0^(1/3)) under a particle-contact plane?
    Scalars only and no cube root: the kernels test every particle with it and call
    ``particle_ground_force`` (whose array arguments cost ~5 % of a sub-step if passed for every
    particle) only for the few it finds."""
    h = z - height
    return particles != 0 and (h <= 0.0 or 8.0 * h * h * h < vol0)


@wp.func
def particle_ground_force(
    ground: GroundStruct,
    ground_k: wp.array(dtype=wp.vec2),  # [M] (X, Pa; sqrt(X / rho) / 2, m/s) per material
    material: int,  # the particle's index into ground_k
    xp: wp.vec3,  # m
    vp: wp.vec3,  # m/s
    m: float,  # kg
    vol0: float,  # rest volume, m^3
    pending: wp.array2d(dtype=wp.float64),  # [2, 4] out: the force is added to row ``slot``, N
    slot: int,
):
    """Force of the ground on one particle that ``touches_ground``, N, and its resting dashpot's
    coefficient c_r, N s/m (module docstring)."""
    h = xp[2] - ground.height
    s = wp.pow(vol0, 1.0 / 3.0)
    depth = 0.5 * s - h
    if depth <= 0.0:
        return wp.vec3(0.0), 0.0
    k_mat = ground_k[material]
    inv_tau = k_mat[1] / s  # 1 / tau = omega / 2
    k = k_mat[0] * s
    # The dashpot 2 zeta m omega = 4 zeta m / tau on the normal velocity; the total never pulls.
    fn = wp.max(k * depth - 4.0 * ground.damping * m * inv_tau * vp[2], 0.0)
    f = wp.vec3(0.0, 0.0, fn)
    speed = wp.sqrt(vp[0] * vp[0] + vp[1] * vp[1])
    if ground.mode != GROUND_SLIP and speed > 0.0:
        ft = wp.min(ground.friction * f[2], ground.friction_rate * m * speed * inv_tau) / speed
        f = wp.vec3(-ft * vp[0], -ft * vp[1], f[2])
    for a in range(3):
        wp.atomic_add(pending, slot, a, wp.float64(f[a]))
    carried = wp.max(m, k * depth * ground.inv_gravity)  # kg, the weight its spring carries / g
    return f, 2.0 * ground.rest_damping * wp.sqrt(k * carried)


@wp.func
def fold_ground_force(
    pending: wp.array2d(dtype=wp.float64),  # [2, 4] forces scattered for this sub-step, N; cleared
    work: wp.array2d(dtype=wp.float64),  # [threads, WORK_ROW] running sums
    col: int,  # first column of the ground impulse in ``work``
    dt: float,
):
    """Ground impulse of this sub-step's particle contact: dt x the forces its scatter used."""
    for row in range(2):
        for a in range(3):
            work[0, col + a] = work[0, col + a] + wp.float64(dt) * pending[row, a]
            pending[row, a] = wp.float64(0.0)


def contact_modulus(ground: GroundPlane, material: MaterialParams, raised: float) -> float:
    """X of the contact spring, Pa: kappa x the material's shear modulus (a fluid, which has none:
    its bulk modulus), raised to ``raised`` (Pa, ``raised_modulus``) and at most its P-wave
    modulus M (module docstring)."""
    p_wave = MODELS[material.model].stiffness(material)
    if material.model == "fluid":
        return p_wave
    return min(max(ground.stiffness * material.mu, raised), p_wave)


def raised_modulus(
    materials: Sequence[MaterialParams],
    volume: np.ndarray,  # [P] rest volumes, m^3
    material: np.ndarray,  # [P] int
    gravity: Sequence[float],  # m/s^2, the scene's
    dx: float,  # the grid's cell, m
) -> np.ndarray:
    """[M] Pa per material: ``LOAD_FACTOR`` x rho |g| V^(1/3), the pressure at the base of a
    compact body of that material's rest volume V resting under the scene's gravity, but no more
    than M (2 s / dx)^2, s its smallest particle spacing: a spring that stiff rings no faster than
    the material's P-wave at the CFL step (module docstring). Rest volumes do not change, so a
    solver rebuilt in the middle of a run on the same cell computes the same springs."""
    g = float(np.linalg.norm(np.asarray(gravity, dtype=np.float64)))
    material = np.asarray(material)
    volume = np.broadcast_to(np.asarray(volume, dtype=np.float64), material.shape)
    sums = np.bincount(material, weights=volume, minlength=len(materials))[: len(materials)]
    raised = np.zeros(len(materials))
    for index, m in enumerate(materials):
        sel = material == index
        if sel.any():
            s = float(np.cbrt(volume[sel].min()))
            step = MODELS[m.model].stiffness(m) * (2.0 * s / dx) ** 2
            raised[index] = min(LOAD_FACTOR * m.density * g * float(np.cbrt(sums[index])), step)
    return raised


def ground_stiffness(
    ground: GroundPlane | None,
    materials: Sequence[MaterialParams],
    raised: Sequence[float],  # [M] Pa, ``raised_modulus``
) -> np.ndarray:
    """[M, 2] per material (X, Pa; sqrt(X / rho) / 2, m/s) of the contact spring (module
    docstring); zeros unless the ground acts on the particles."""
    if ground is None or not ground.on_particles:
        return np.zeros((len(materials), 2), dtype=np.float32)
    rows = []
    for m, w in zip(materials, raised, strict=True):
        x = contact_modulus(ground, m, float(w))
        rows.append((x, 0.5 * math.sqrt(x / m.density)))
    return np.array(rows, dtype=np.float32)


def pack_contact(
    ground: GroundPlane,
    gravity: Sequence[float],  # m/s^2, the scene's
    x: np.ndarray,  # [P, 3] particles at the start, m
    volume: np.ndarray,  # [P] rest volumes, m^3
    cfl: float,  # the solver's CFL number
) -> GroundStruct:
    """The kernels' struct of a particle-contact ground (module docstring): the springs push from
    ``contact_plane``; the resting dashpot acts below sqrt(|g| s), s the smallest particle spacing,
    with 1 / |g| (both 0 without gravity, which turns it off); the friction's cap is m |v_t| /
    (cfl tau)."""
    struct = ground.pack()
    struct.height = contact_plane(ground, x, volume)
    g = float(np.linalg.norm(np.asarray(gravity, dtype=np.float64)))
    s = float(np.cbrt(np.min(volume))) if np.size(volume) else 0.0
    struct.rest_speed = math.sqrt(g * s) if g > 0.0 else 0.0
    struct.inv_gravity = 1.0 / g if g > 0.0 else 0.0
    struct.friction_rate = 1.0 / cfl
    return struct


def contact_plane(ground: GroundPlane, x: np.ndarray, volume: np.ndarray) -> float:
    """Height of the plane the contact springs push from, m (x [P, 3] m, volume [P] m^3 at the start).

    The ground's own height, lowered by the deepest overlap of a starting particle's surface with
    it (at most half that particle's spacing): particles given with their lowest centres on the
    floor would otherwise start with the springs compressed by half a spacing, which throws the
    body off the ground (a 10 cm wood block jumped 8 cm). Such a body rests with its lowest
    particles on the plane instead. The registered scenes (``physgm.sim.scenes``) place the
    material's surface on the floor, so for them the plane is the ground's own.
    A ground whose ``contact_height`` is set keeps that plane.
    """
    if ground.contact_height is not None:
        return ground.contact_height
    half = 0.5 * np.cbrt(np.asarray(volume, dtype=np.float64))
    overlap = np.minimum(ground.height + half - np.asarray(x, dtype=np.float64)[:, 2], half)
    return ground.height - max(float(overlap.max()), 0.0)


def contact_wave_speed(
    ground: GroundPlane | None,
    materials: Sequence[MaterialParams],
    volume: np.ndarray,  # [P] rest volumes, m^3
    material: np.ndarray,  # [P] int
    dx: float,
    gravity: Sequence[float],  # m/s^2, the scene's
) -> float:
    """Speed c the contact springs need in dt = cfl dx / c (module docstring), m/s; 0 without them."""
    if ground is None or not ground.on_particles:
        return 0.0
    volume = np.broadcast_to(np.asarray(volume, dtype=np.float64), np.shape(material))
    raised = raised_modulus(materials, volume, material, gravity, dx)
    c = 0.0
    for index, m in enumerate(materials):
        sel = material == index
        if sel.any():
            s = float(volume[sel].min()) ** (1.0 / 3.0)
            x = contact_modulus(ground, m, float(raised[index]))
            c = max(c, math.sqrt(x / m.density) * dx / (2.0 * s))
    return c
