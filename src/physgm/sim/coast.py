"""Flight in closed form: the first fall (``ballistic_frames``), and a body that left the ground
moving rigidly until it is back within reach of it (issue 25).

A stiff elastic object dropped on the floor spends most of a clip in the air between bounces,
and the explicit MPM pays its wave-speed sub-step all the way (rubber: ~1,600 sub-steps a
frame). In flight only the body's own vibration changes its shape. ``coast`` replaces those
frames by the rigid motion of the particles: the centre of mass falls ballistically and the
orientation turns torque-free about the conserved angular momentum (``physgm.sim.rigid``). Each
particle keeps, in the body frame, its deformation F and its velocity relative to the rigid
motion, so the vibration resumes where it paused when the MPM takes over again, ``gap`` above
the ground (the same margin as the ballistic prefix of the first fall).

What it leaves out is the vibration during the flight, in two ways (``vibration``):
- in the air, points sit where the vibration paused instead of swinging about it: at most its
  amplitude, size x strain / 2 + relative speed / omega_1, where omega_1 = pi c_s / size is the
  lowest elastic frequency of a compact body of that size (a standing shear wave across it;
  slender bodies ring lower and are under-estimated);
- at the next impact the vibration meets the ground in another phase, and the rebound changes
  (docs/measurements_sim.md section 12: left out of the bound, it moved a rubber block's next
  apex by centimetres). The bound is the vibration's whole energy turned into speed, kept for
  the rest of the clip.
The caller coasts only while both fit its share of the pixel bound. Fluids never coast.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.state import ParticleState
from physgm.sim.rigid import ContactParams, RigidBody, RigidSimulator, mass_properties, quat_to_matrix

STEPS_PER_FRAME = 16  # rigid steps per frame while looking for the return within reach of the ground


@dataclass
class Coast:
    """Frames of a flight in closed form and the state the MPM resumes from.

    Attributes:
        x: [K, P, 3] particle positions of the K coasted frames, m.
        F: [K, P, 3, 3] their deformation gradients (the take-off F turned with the body).
        v: [P, 3] particle velocities at the last coasted frame, m/s.
        C: [P, 3, 3] APIC affine velocities there, 1/s.
        predicted_px: the error bound of the module docstring, pixels (``next_flight`` sets it).
    """

    x: np.ndarray
    F: np.ndarray
    v: np.ndarray
    C: np.ndarray
    predicted_px: float

    @property
    def frames(self) -> int:
        return self.x.shape[0]


def fall_time(height: float, vz: float, gz: float) -> float:
    """First t > 0 at which a point ``height`` (m, > 0) above a plane, rising at ``vz`` (m/s) under
    gravity ``gz`` (m/s^2), reaches it; inf without downward gravity."""
    if gz >= 0.0:
        return math.inf
    return (-vz - math.sqrt(vz * vz - 2.0 * gz * height)) / gz


def ballistic_frames(
    x: np.ndarray, v0: np.ndarray, scene: Scene, frame_dt: float, n_frames: int, gap: float
) -> int:
    """Number of leading frames (incl. frame 0) during which the object is in free flight.

    Only for a body moving as a whole (uniform v0), with nothing prescribed, while its lowest
    point stays ``gap`` (m) above the ground: there uniform gravity leaves it undeformed.
    """
    if scene.ground is None or scene.boxes or len(x) == 0 or np.ptp(v0, axis=0).max() > 1e-9:
        return 1
    height = x[:, 2].min() - scene.ground.height - gap
    gz = float(scene.gravity[2])
    if height <= 0 or gz >= 0:
        return 1
    t_hit = fall_time(float(height), float(v0[0, 2]), gz)
    return int(min(n_frames, max(1, math.floor(t_hit / frame_dt) + 1)))


def _skew(w: np.ndarray) -> np.ndarray:
    """[w]x: the matrix of the cross product w x (.)."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


@dataclass
class RigidMotion:
    """The rigid part of particle velocities (momentum and angular momentum kept) and the rest."""

    com: np.ndarray  # [3] m
    v_com: np.ndarray  # [3] m/s
    omega: np.ndarray  # [3] rad/s, I^-1 L about the centre of mass
    v_rel: np.ndarray  # [P, 3] m/s, what the rigid motion leaves: the vibration's velocity


def rigid_motion(
    x: np.ndarray, v: np.ndarray, mass: np.ndarray
) -> RigidMotion:  # float64 [P, 3], [P, 3], [P]
    """Split velocities into the rigid motion with the same momentum and angular momentum, and the rest."""
    total, com, inertia = mass_properties(x, mass)
    v_com = mass @ v / total
    r = x - com
    omega = np.linalg.solve(inertia, mass @ np.cross(r, v - v_com))
    return RigidMotion(com, v_com, omega, v - v_com - np.cross(omega, r))


@dataclass
class Vibration:
    """How much a body deviates from rigid motion (``vibration``).

    Attributes:
        amplitude: m, the root-mean-square distance a point could be moved by the vibration: size x
            strain / 2 plus relative speed / omega_1 (mass-weighted over the particles).
        rebound_speed: m/s, sqrt(2 E_vib / M): the most the centre of mass could gain or lose at the
            next impact if all the vibration's energy E_vib (kinetic + elastic) went into it or
            came from it. Which one depends on the phase of the vibration at that impact, which
            coasting does not keep.
    """

    amplitude: float
    rebound_speed: float


def vibration(
    x: np.ndarray,  # [P, 3] m
    v: np.ndarray,  # [P, 3] m/s
    F: np.ndarray,  # [P, 3, 3]
    mass: np.ndarray,  # [P] kg
    volume: np.ndarray,  # [P] rest volumes, m^3
    material: MaterialParams,
) -> Vibration:
    """The body's deviation from rigid motion; infinite for a fluid (no shear stiffness)."""
    if material.model == "fluid":
        return Vibration(math.inf, math.inf)
    x, v, F, mass, volume = (np.asarray(a, dtype=np.float64) for a in (x, v, F, mass, volume))
    total, v_rel = float(mass.sum()), rigid_motion(x, v, mass).v_rel
    size = float(np.ptp(x, axis=0).max())
    omega_1 = math.pi * math.sqrt(material.mu / material.density) / max(size, 1e-9)
    # Green strain (rotation-free), rows of 9; a batched matmul, not einsum, which is twice as slow
    # here (this runs after every frame in the air).
    strain = np.matmul(F.transpose(0, 2, 1), F).reshape(-1, 9)
    strain[:, ::4] -= 1.0
    strain *= 0.5
    squared = np.einsum("pi,pi->p", strain, strain)  # |E|^2
    w = mass / total
    strain_rms = math.sqrt(float(w @ squared))
    speed_rms = math.sqrt(float(w @ (v_rel * v_rel).sum(1)))
    trace = strain[:, ::4].sum(1)
    elastic = volume @ (material.mu * squared + 0.5 * material.lam * trace * trace)
    kinetic = 0.5 * float(mass @ (v_rel * v_rel).sum(1))
    return Vibration(
        0.5 * size * strain_rms + speed_rms / omega_1,
        math.sqrt(2.0 * (kinetic + float(elastic)) / total),
    )


def coast(
    x: np.ndarray,  # [P, 3] m, at the frame the body is in flight
    v: np.ndarray,  # [P, 3] m/s
    F: np.ndarray,  # [P, 3, 3]
    C: np.ndarray,  # [P, 3, 3] 1/s
    mass: np.ndarray,  # [P] kg
    ground_height: float,  # m
    gravity: np.ndarray,  # [3] m/s^2
    frame_dt: float,  # s
    max_frames: int,
    gap: float,  # m: the MPM takes over before the lowest point comes closer to the ground
) -> Coast | None:
    """The frames after the current one the body flies through above ``ground_height + gap``.

    Returns None when not even one whole frame fits (the body is too low or falling onto the
    ground within the frame). ``predicted_px`` is left 0 (``next_flight`` fills it in).
    """
    x64, v64, m64 = (np.asarray(a, dtype=np.float64) for a in (x, v, mass))
    floor = ground_height + gap
    if float(x64[:, 2].min()) <= floor:
        return None
    body = RigidBody.from_particles(x64, m64)
    # The rotation turns torque-free (the rigid path's integrator, without gravity or planes);
    # the centre of mass falls in closed form, so the flight has no integration error in it.
    sim = RigidSimulator(
        body,
        ContactParams(ground_height=None, gravity=(0.0, 0.0, 0.0)),
        RigidSimulator.initial_state(body, x64, m64, v64),
    )
    g = np.asarray(gravity, dtype=np.float64)
    start = rigid_motion(x64, v64, m64)
    v_com0, omega0, v_rel = start.v_com, start.omega, start.v_rel
    r = x64 - body.com
    poses = []
    dt = frame_dt / STEPS_PER_FRAME
    while len(poses) < max_frames:
        low = math.inf
        for _ in range(STEPS_PER_FRAME):
            sim.step(dt)
            t = sim.time
            com_z = body.com[2] + v_com0[2] * t + 0.5 * g[2] * t * t
            low = min(low, float((body.points @ quat_to_matrix(sim.state.q).T)[:, 2].min() + com_z))
        if low <= floor:
            break
        t = sim.time
        com = body.com + v_com0 * t + 0.5 * g * t * t
        poses.append((quat_to_matrix(sim.state.q), com, v_com0 + g * t, sim.omega()))
    if not poses:
        return None
    xs = np.stack([r @ R.T + com for R, com, _, _ in poses]).astype(np.float32)
    Fs = np.stack([np.einsum("ij,pjk->pik", R, F) for R, _, _, _ in poses]).astype(np.float32)
    R, com, v_com, omega = poses[-1]
    v_end = v_com + np.cross(omega, r @ R.T) + v_rel @ R.T
    # C is the velocity gradient: its vibration part turns with the body, its spin part is the
    # spin at the end.
    C_vib = np.asarray(C, np.float64) - _skew(omega0)
    C_end = np.einsum("ij,pjk,lk->pil", R, C_vib, R) + _skew(omega)
    return Coast(xs, Fs, v_end.astype(np.float32), C_end.astype(np.float32), 0.0)


def next_flight(
    state: ParticleState,  # at the end of the frame just simulated
    mass: np.ndarray,  # [P] kg
    volume: np.ndarray,  # [P] rest volumes, m^3
    material: MaterialParams,
    scene: Scene,  # gravity and the ground
    frame_dt: float,  # s
    frames_left: int,  # frames of the clip after this one
    gap: float,  # m, the MPM takes over before the lowest point comes closer to the ground
    px_per_m: float,  # at the output camera
    budget_px: float,  # of the pixel bound, what the left-out vibration may cost
) -> Coast | None:
    """The coming frames of a flight if the body is in the air, at least two frames fit, and the
    vibration it leaves out fits ``budget_px``: its amplitude in the air, plus the rebound it
    could change kept from the next impact to the end of the clip (half of it on average over
    those frames). Else None."""
    ground = scene.ground.height
    if frames_left < 2 or float(state.x[:, 2].min()) <= ground + gap:
        return None
    vib = vibration(state.x, state.v, state.F, mass, volume, material)
    # The centre of mass falls to ground + gap later than the lowest point: a bound on the flight,
    # so on the clip left after it, checked before the flight is worked out.
    com_z = float(mass @ state.x[:, 2]) / float(mass.sum()) - ground - gap
    vz = float(mass @ state.v[:, 2]) / float(mass.sum())
    least_tail = max(frames_left * frame_dt - fall_time(com_z, vz, float(scene.gravity[2])), 0.0)
    if (vib.amplitude + 0.5 * vib.rebound_speed * least_tail) * px_per_m > budget_px:
        return None
    flight = coast(
        state.x,
        state.v,
        state.F,
        state.C,
        mass,
        ground,
        np.asarray(scene.gravity),
        frame_dt,
        frames_left,
        gap,
    )
    if flight is None or flight.frames < 2:
        return None
    tail = (frames_left - flight.frames) * frame_dt  # s of the clip after the flight
    flight.predicted_px = px_per_m * (vib.amplitude + 0.5 * vib.rebound_speed * tail)
    return flight if flight.predicted_px <= budget_px else None
