"""Rigid-body path: an object too stiff to deform visibly, dropped on the ground or thrown at a wall.

The body is the particle set (mass and inertia tensor from the particles); its contact points are
the vertices of their convex hull. Obstacles are planes: the ground and the static walls of a
scene. Each step: gravity, contact impulses on the touching points (projected Gauss-Seidel on the
normal impulse and on a Coulomb-clamped friction impulse; a bounce is Poisson's: the impulse that
stops the approach, then restitution times it), then free motion. Points that reach a plane within
a millisecond of the first share its impact. A step that would carry the body through a plane is
cut at the time of impact, so the bounce happens at the right place and speed whatever the step
size. Angular momentum (world frame) is the rotational state, which keeps it exactly constant in
free flight and gets the torque-free tumbling of an asymmetric body right.

Numpy float64 on the CPU: a body is one 13-number state, far too small for a kernel launch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import ConvexHull, QhullError


@dataclass
class RigidBody:
    """Mass properties and contact points of a rigid body, in its rest pose.

    Attributes:
        mass: kg.
        com: [3] rest centre of mass, m.
        inertia: [3, 3] inertia tensor about the centre of mass, rest orientation, kg m^2.
        points: [H, 3] contact points relative to the centre of mass, m (rest orientation).
    """

    mass: float
    com: np.ndarray  # [3]
    inertia: np.ndarray  # [3, 3]
    points: np.ndarray  # [H, 3]

    @staticmethod
    def from_particles(
        x: np.ndarray,  # [P, 3] rest positions, m
        mass: np.ndarray,  # [P] kg
        contact_points: np.ndarray | None = None,  # [Q, 3] surface points, m; default: the particles
    ) -> RigidBody:
        """Mass, centre of mass and inertia tensor from particles; contacts on the convex hull."""
        x = np.asarray(x, dtype=np.float64)
        m = np.asarray(mass, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != 3 or m.shape != (x.shape[0],):
            raise ValueError(
                f"RigidBody.from_particles needs x [P, 3] and mass [P], got {x.shape} and {m.shape}"
            )
        if not float(m.sum()) > 0:
            raise ValueError(
                "RigidBody.from_particles: total mass must be positive; check particle volumes and density"
            )
        total, com, inertia = mass_properties(x, m)
        pts = x if contact_points is None else np.asarray(contact_points, dtype=np.float64)
        return RigidBody(total, com, inertia, _hull_vertices(pts) - com)


def mass_properties(x: np.ndarray, mass: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Total mass (kg), centre of mass [3] (m) and inertia tensor about it [3, 3] (kg m^2) of
    particles x [P, 3] with masses [P] (float64)."""
    total = float(mass.sum())
    com = mass @ x / total
    r = x - com
    inertia = np.eye(3) * float(mass @ (r * r).sum(1)) - np.einsum("p,pi,pj->ij", mass, r, r)
    # A degenerate (flat or linear) particle set has a singular inertia: add the tensor of a thin
    # shell so the body still rotates, without changing the inertia of a full body noticeably.
    inertia += np.eye(3) * 1e-9 * max(float(np.trace(inertia)), total * 1e-6)
    return total, com, inertia


def _hull_vertices(points: np.ndarray) -> np.ndarray:
    """Convex hull vertices [H, 3] (all points if the set is flat or tiny)."""
    if len(points) < 5:
        return points
    try:
        return points[ConvexHull(points).vertices]
    except QhullError:
        return points


@dataclass
class ContactParams:
    """Ground contact of the rigid path.

    Attributes:
        restitution: ratio of rebound to impact normal speed.
        friction: Coulomb friction coefficient mu.
        ground_height: z of the ground plane, m (None: no ground).
        walls: further planes ((nx, ny, nz), d): points p with n . p >= d are free, n a unit
            normal pointing to the free side (static walls of a scene, see ``static_walls``).
        gravity: [3] m/s^2.
        min_bounce_speed: impacts slower than this (m/s) do not bounce, so a body comes to rest
            instead of chattering in ever smaller bounces.
        impact_time: s; hull points that reach a plane within this time of the first one share
            its impact. A real impact lasts about a millisecond, so a flat base that lands a hair
            off level lands on the whole base at once, rather than on one edge first, which
            would spin the body and tip it over.
        impact_reach: the farthest from the plane a point may be and share the impact, as a
            share of the body's size. A faster impact is shorter, so at 30 m/s a cube that lands
            on a corner lands on that corner, not on a face whose other corners are 9-17 mm up.
        iterations: projected Gauss-Seidel sweeps per contact solve.
        max_contacts: touching points kept per step (extreme points of the contact patch).
    """

    restitution: float = 0.5
    friction: float = 0.3
    ground_height: float | None = 0.0
    walls: tuple[tuple[tuple[float, float, float], float], ...] = ()
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    min_bounce_speed: float = 0.05
    impact_time: float = 1e-3
    impact_reach: float = 0.02
    iterations: int = 30
    max_contacts: int = 8


@dataclass
class RigidState:
    """World-frame state: centre of mass x [3] m, orientation q [4] (w, x, y, z), velocity v [3]
    m/s, angular momentum L [3] kg m^2/s."""

    x: np.ndarray
    q: np.ndarray
    v: np.ndarray
    L: np.ndarray


@dataclass
class RigidTrajectory:
    """Per-frame rigid poses. Particle X (rest) is at ``rotations[t] @ (X - rest_com) + coms[t]``.

    Attributes:
        rotations: [T, 3, 3].  coms: [T, 3] m.  velocities: [T, 3] m/s.  omegas: [T, 3] rad/s.
        rest_com: [3] m.  frame_dt: s.  steps: integration steps taken.
        rest_frame: first frame from which the body was held at rest (None: never at rest).
    """

    rotations: np.ndarray
    coms: np.ndarray
    velocities: np.ndarray
    omegas: np.ndarray
    rest_com: np.ndarray
    frame_dt: float
    steps: int
    rest_frame: int | None = None
    events: list[tuple[float, float, float]] = field(default_factory=list)  # (time, vn_in, vn_out) impacts

    def transform(self, x: np.ndarray, t: int) -> np.ndarray:
        """Positions [P, 3] at frame t of rest points x [P, 3]."""
        return (x - self.rest_com) @ self.rotations[t].T + self.coms[t]


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _rotate_quat(q: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """q advanced by a rotation of omega * dt (world frame), exactly via the exponential map."""
    angle = float(np.linalg.norm(omega)) * dt
    if angle < 1e-15:
        return q
    axis = omega / np.linalg.norm(omega)
    s = math.sin(angle / 2)
    dw, dx, dy, dz = math.cos(angle / 2), axis[0] * s, axis[1] * s, axis[2] * s
    w, x, y, z = q
    out = np.array(
        [
            dw * w - dx * x - dy * y - dz * z,
            dw * x + dx * w + dy * z - dz * y,
            dw * y - dx * z + dy * w + dz * x,
            dw * z + dx * y - dy * x + dz * w,
        ]
    )
    return out / np.linalg.norm(out)


def static_walls(
    boxes,  # VelocityBox sequence of the scene
    lo: np.ndarray,  # [3] object's lower corner at rest, m
    hi: np.ndarray,  # [3] upper corner, m
) -> list[tuple[tuple[float, float, float], float]] | None:
    """The scene's boxes as contact planes for the rigid path, or None if it cannot take them.

    A box that never moves (zero velocity, active from t = 0 on) and lies beside the object acts
    on it as the plane of its face towards the object (the push scene's wall). A moving box (a
    grip) or a still one overlapping the object (a clamp) prescribes motion: None.
    """
    planes = []
    for box in boxes:
        if any(c != 0.0 for c in box.velocity) or box.start > 0.0:
            return None
        b_lo, b_hi = np.asarray(box.lo, np.float64), np.asarray(box.hi, np.float64)
        gaps = np.concatenate([b_lo - hi, lo - b_hi])  # [6]: box above the object / below, per axis
        side = int(np.argmax(gaps))
        if gaps[side] <= 0.0:
            return None  # overlaps the object on every axis
        axis = side % 3
        normal = [0.0, 0.0, 0.0]
        if side < 3:  # the box is on the + side: the object stays below its lower face
            normal[axis] = -1.0
            planes.append((tuple(normal), -float(b_lo[axis])))
        else:
            normal[axis] = 1.0
            planes.append((tuple(normal), float(b_hi[axis])))
    return planes


def _tangents(n: np.ndarray) -> np.ndarray:
    """Rows (n, t1, t2): a right-handed frame around the unit normal n ((x, y) for the ground)."""
    helper = np.array([0.0, 1.0, 0.0]) if abs(n[2]) > 0.9 else np.array([0.0, 0.0, 1.0])
    t1 = np.cross(helper, n)
    t1 /= np.linalg.norm(t1)
    return np.stack([n, t1, np.cross(n, t1)])


class RigidSimulator:
    """Integrates one rigid body among contact planes; see the module docstring."""

    def __init__(self, body: RigidBody, contact: ContactParams, state: RigidState):
        if not 0.0 <= contact.restitution <= 1.0:
            raise ValueError(f"restitution must be in [0, 1], got {contact.restitution}")
        if contact.friction < 0:
            raise ValueError(f"friction must be >= 0, got {contact.friction}")
        self.body, self.contact, self.state = body, contact, state
        self.inv_mass = 1.0 / body.mass
        self.inv_inertia_body = np.linalg.inv(body.inertia)
        self.gravity = np.asarray(contact.gravity, dtype=np.float64)
        self.time = 0.0
        self.steps = 0
        self.events: list[tuple[float, float, float]] = []
        # Contact planes (n, d): the ground first, then the walls.
        planes = [] if contact.ground_height is None else [((0.0, 0.0, 1.0), contact.ground_height)]
        planes += list(contact.walls)
        self.normals = np.array([n for n, _ in planes], dtype=np.float64).reshape(-1, 3)  # [K, 3]
        if len(self.normals) and not np.allclose(np.linalg.norm(self.normals, axis=1), 1.0):
            raise ValueError(f"contact plane normals must be unit vectors, got {self.normals.tolist()}")
        self.offsets = np.array([d for _, d in planes], dtype=np.float64)  # [K]
        self.frames = [_tangents(n) for n in self.normals]  # per plane: rows (n, t1, t2)
        self._warm: dict[tuple[int, int], np.ndarray] = {}  # (plane, hull index) -> last impulses
        # Points closer to a plane than this count as touching (1e-4 of the body size: invisible).
        self.slop = 1e-4 * float(np.abs(body.points).max()) + 1e-9
        self.reach = contact.impact_reach * 2.0 * float(np.abs(body.points).max())  # see ContactParams

    @staticmethod
    def initial_state(body: RigidBody, x: np.ndarray, mass: np.ndarray, v: np.ndarray) -> RigidState:
        """State at rest pose from per-particle velocities v [P, 3] (momentum and spin kept)."""
        x, mass, v = (np.asarray(a, dtype=np.float64) for a in (x, mass, v))
        lin = (mass[:, None] * v).sum(0) / body.mass
        ang = (mass[:, None] * np.cross(x - body.com, v - lin)).sum(0)
        return RigidState(body.com.copy(), np.array([1.0, 0.0, 0.0, 0.0]), lin, ang)

    def omega(self, q: np.ndarray | None = None, L: np.ndarray | None = None) -> np.ndarray:
        """World angular velocity I_w^-1 L for orientation q (default: the current one)."""
        rot = quat_to_matrix(self.state.q if q is None else q)
        return rot @ (self.inv_inertia_body @ (rot.T @ (self.state.L if L is None else L)))

    def _distances(self, x: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distances [K, H] of the hull points to the planes, and their arms [H, 3]."""
        arms = self.body.points @ quat_to_matrix(q).T  # [H, 3] world offsets from the com
        return ((x + arms) @ self.normals.T - self.offsets).T, arms

    def _gap(self, x: np.ndarray, q: np.ndarray) -> float:
        """Smallest signed distance of any hull point to any plane (inf without planes), m."""
        dist = self._distances(x, q)[0]
        return float(dist.min()) if dist.size else math.inf

    def _drift(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Free motion over dt with the current velocities (midpoint rule for the rotation)."""
        s = self.state
        half = _rotate_quat(s.q, self.omega(), 0.5 * dt)
        return s.x + s.v * dt, _rotate_quat(s.q, self.omega(half), dt)

    def step(self, dt: float) -> None:
        """Advance dt: gravity, contact impulses, free motion cut at the time of impact."""
        s = self.state
        s.v = s.v + self.gravity * dt
        remaining = dt
        planes = len(self.offsets) > 0
        for attempt in range(4):  # at most a few impacts inside one step
            if planes:
                self._solve_contacts()
            x1, q1 = self._drift(remaining)
            if not planes:
                s.x, s.q = x1, q1
                break
            # Per plane: a body resting on the ground may still be about to hit a wall.
            h0 = self._distances(s.x, s.q)[0].min(axis=1)  # [K]
            h1 = self._distances(x1, q1)[0].min(axis=1)
            crossing = (h1 < -self.slop) & (h0 > self.slop)
            if not crossing.any() or attempt == 3:
                s.x, s.q = x1, q1
                break
            # The body would cross a plane during this step: move it to the first contact and let
            # the next pass resolve the impact with the pre-impact velocity.
            frac = max(0.0, min(1.0, float((h0[crossing] / (h0[crossing] - h1[crossing])).min())))
            s.x, s.q = self._drift(frac * remaining)
            remaining *= 1.0 - frac
        if planes:
            # Remove residual penetration by moving the body, never by adding velocity.
            depth = -self._distances(s.x, s.q)[0].min(axis=1)  # [K]
            for k in np.flatnonzero(depth > 0):
                s.x = s.x + self.normals[k] * depth[k]
        self.time += dt
        self.steps += 1

    def _contact_set(self) -> tuple[list[tuple[int, int]], np.ndarray, np.ndarray]:
        """(plane, hull point) pairs in contact, their arms [C, 3] and contact frames [C, 3, 3].

        On a plane some point touches, the set also holds the points that will reach it within
        ``impact_time`` at their present speed, up to ``impact_reach`` away (``ContactParams``).
        """
        s = self.state
        dist, arms = self._distances(s.x, s.q)
        approach = -(s.v + np.cross(self.omega(), arms)) @ self.normals.T  # [H, K] speeds towards
        keys, frames = [], []
        for k, frame in enumerate(self.frames):
            if not (dist[k] <= self.slop).any():
                continue
            ahead = np.maximum(approach[:, k], 0.0) * self.contact.impact_time
            reach = self.slop + np.minimum(ahead, self.reach)
            idx = np.flatnonzero(dist[k] <= reach)
            if len(idx) > self.contact.max_contacts:
                # Keep the extreme points of the patch (they carry the torque) plus the deepest.
                angles = np.linspace(0, 2 * np.pi, self.contact.max_contacts - 1, endpoint=False)
                dirs = np.stack([np.cos(angles), np.sin(angles)], 1)  # [D, 2]
                in_plane = arms[idx] @ frame[1:].T  # [n, 2] tangential coordinates
                keep = {int(np.argmin(dist[k, idx]))} | {int(i) for i in np.argmax(in_plane @ dirs.T, axis=0)}
                idx = idx[sorted(keep)]
            keys += [(k, int(h)) for h in idx]
            frames += [frame] * len(idx)
        hull = [h for _, h in keys]
        return keys, arms[hull], np.array(frames).reshape(-1, 3, 3)

    def _solve_contacts(self) -> None:
        """Contact impulses in two phases (Poisson's impact law).

        Compression: normal impulses that stop every contact point's approach, with Coulomb
        friction. Restitution: each bouncing point then gets ``restitution`` times its compression
        impulse, and friction is solved again under the larger normal impulse. On a single point
        this is the usual rebound at ``restitution`` times the impact speed. On a face it keeps
        the impulses in the proportion that stopped the face, so a face that lands flat rebounds
        flat: a solve that asked each point for its own rebound speed would share the impulse
        among a face's points in the sweep's order and spin the body.
        """
        keys, arms, axes = self._contact_set()
        if not keys:
            self._warm = {}
            return
        s, c = self.state, self.contact
        m_inv = self.inv_mass
        rot = quat_to_matrix(s.q)
        i_inv = rot @ self.inv_inertia_body @ rot.T  # world inverse inertia
        n_c = len(keys)
        # Jacobians: rows (normal, tangent 1, tangent 2) per contact act on (v, omega).
        ang = np.cross(arms[:, None, :], axes)  # [C, 3, 3]: r x axis
        jac_ang = ang.reshape(3 * n_c, 3)
        jac_lin = axes.reshape(3 * n_c, 3)
        delassus = m_inv * jac_lin @ jac_lin.T + jac_ang @ i_inv @ jac_ang.T  # [3C, 3C]
        omega = i_inv @ s.L
        vel = jac_lin @ s.v + jac_ang @ omega  # [3C]
        vn_in = vel[0::3].copy()
        bouncing = vn_in < -c.min_bounce_speed
        lam = np.zeros(3 * n_c)
        for j, key in enumerate(keys):  # warm start from the last step's impulses on the same points
            if key in self._warm and not bouncing[j]:
                lam[3 * j : 3 * j + 3] = self._warm[key]
        vel = vel + delassus @ lam
        diag = np.diag(delassus).copy()
        self._sweeps(lam, vel, delassus, diag, normals=True)
        if bouncing.any() and c.restitution > 0.0:
            kick = np.zeros(3 * n_c)
            kick[0::3] = np.where(bouncing, c.restitution * lam[0::3], 0.0)
            vel += delassus @ kick
            lam += kick
            self._sweeps(lam, vel, delassus, diag, normals=False)
        impulses = np.einsum("cj,cjk->ck", lam.reshape(n_c, 3), axes)  # [C, 3] world
        s.v = s.v + m_inv * impulses.sum(0)
        s.L = s.L + np.cross(arms, impulses).sum(0)
        self._warm = {key: lam[3 * j : 3 * j + 3].copy() for j, key in enumerate(keys)}
        if bouncing.any():
            j = int(np.argmin(vn_in))
            self.events.append((self.time, float(vn_in[j]), float(vel[3 * j])))

    def _sweeps(
        self, lam: np.ndarray, vel: np.ndarray, delassus: np.ndarray, diag: np.ndarray, normals: bool
    ) -> None:
        """Projected Gauss-Seidel on the impulses lam [3C] in place, vel [3C] kept equal to the
        contact velocities they give: normal impulses >= 0 that stop the approach (when
        ``normals``; otherwise they stay as they are) and friction inside mu times each normal."""
        n_c = len(lam) // 3
        for _ in range(self.contact.iterations):
            change = 0.0
            for j in range(n_c):
                i = 3 * j
                if normals:
                    new_n = max(0.0, lam[i] - vel[i] / diag[i])
                    d = new_n - lam[i]
                    if d != 0.0:
                        vel += delassus[:, i] * d
                        lam[i] = new_n
                        change = max(change, abs(d))
                # Friction: drive the tangential velocity to zero inside the Coulomb disc mu * jn.
                t_old = lam[i + 1 : i + 3].copy()
                t_new = t_old - vel[i + 1 : i + 3] / diag[i + 1 : i + 3]
                norm = math.hypot(t_new[0], t_new[1])
                limit = self.contact.friction * lam[i]
                if norm > limit:
                    t_new *= limit / norm
                d_t = t_new - t_old
                if d_t[0] != 0.0 or d_t[1] != 0.0:
                    vel += delassus[:, i + 1 : i + 3] @ d_t
                    lam[i + 1 : i + 3] = t_new
                    change = max(change, abs(d_t[0]), abs(d_t[1]))
            if change < 1e-12 * (1.0 + np.abs(lam).max()):
                break

    def kinetic_energy(self) -> float:
        s = self.state
        return 0.5 * self.body.mass * float(s.v @ s.v) + 0.5 * float(s.L @ self.omega())

    def max_point_speed(self) -> float:
        """Largest speed of a contact point (hull vertex), m/s: the body's visible speed."""
        s = self.state
        arms = self.body.points @ quat_to_matrix(s.q).T
        return float(np.linalg.norm(s.v + np.cross(self.omega(), arms), axis=1).max())

    def run(
        self, n_frames: int, frame_dt: float, dt: float, rest_speed: float = 0.0, rest_frames: int = 5
    ) -> RigidTrajectory:
        """Simulate n_frames frames (frame 0 = initial pose) with steps of about dt.

        Frames are held once the visible speed stayed below ``rest_speed`` (m/s) for
        ``rest_frames`` consecutive frames while touching a plane.
        """
        n_sub = max(1, math.ceil(frame_dt / dt - 1e-9))
        rots, coms, vels, omegas = [], [], [], []
        quiet, rest_frame = 0, None

        def record() -> None:
            rots.append(quat_to_matrix(self.state.q))
            coms.append(self.state.x.copy())
            vels.append(self.state.v.copy())
            omegas.append(self.omega())

        record()
        for frame in range(1, n_frames):
            if rest_frame is None:
                for _ in range(n_sub):
                    self.step(frame_dt / n_sub)
                touching = self._gap(self.state.x, self.state.q) <= self.slop
                quiet = quiet + 1 if (touching and self.max_point_speed() < rest_speed) else 0
                if quiet >= rest_frames:
                    rest_frame = frame
                    self.state.v[:] = 0.0
                    self.state.L[:] = 0.0
            record()
        return RigidTrajectory(
            np.stack(rots),
            np.stack(coms),
            np.stack(vels),
            np.stack(omegas),
            self.body.com.copy(),
            frame_dt,
            self.steps,
            rest_frame,
            list(self.events),
        )
