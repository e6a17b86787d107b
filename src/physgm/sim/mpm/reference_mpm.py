"""Plain numpy twin of one MLS-MPM sub-step (p2g, grid update, g2p), float64, for tests only.

Mirrors ``kernels.p2g`` / ``grid_update`` / ``g2p`` node by node with explicit loops, the
ground's particle contact (``particle_ground``) included; the constitutive update comes from
``constitutive.reference``.
"""

from __future__ import annotations

import numpy as np

from physgm.sim.constitutive import reference as cref
from physgm.sim.mpm.boundary import NET_DEPTH
from physgm.sim.mpm.kernels import NODE_MASS_FLOOR
from physgm.sim.mpm.particle_ground import ground_stiffness, pack_contact, raised_modulus


def _weights(fx: np.ndarray) -> np.ndarray:  # fx: [3] -> [3 (node), 3 (axis)]
    return np.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2])


def _box_velocity(box, pos, t, v):
    if t < box.start:
        return v
    moving = t < box.stop
    if not moving and not box.hold:
        return v
    shift = np.asarray(box.velocity) * (min(t, box.stop) - box.start)
    lo, hi = np.asarray(box.lo) + shift, np.asarray(box.hi) + shift
    if np.any(pos < lo) or np.any(pos > hi):
        return v
    target = np.asarray(box.velocity, float) if moving else np.zeros(3)
    return np.where(box.axes, target, v)


def _ground_velocity(ground, pos, dx, v):
    if ground is None:
        return v
    depth = ground.held_depth
    limit = ground.height if depth == 0 else ground.height - (depth - 0.5) * dx
    if ground.on_particles:
        limit = ground.height - NET_DEPTH * dx
    if pos[2] > limit:
        return v
    if ground.mode == "sticky":
        return np.zeros(3)
    if v[2] >= 0:
        return v
    vt = np.array([v[0], v[1], 0.0])
    if ground.mode == "slip":
        return vt
    n = np.linalg.norm(vt)
    if n <= -ground.friction * v[2]:
        return np.zeros(3)
    return vt * (1 + ground.friction * v[2] / n)


def _particle_ground_force(ground, k_mat, x, v, m, vol0, inv_gravity=0.0, friction_rate=1.0):
    """The ground's penalty and friction force on one particle, N, and its resting dashpot's
    coefficient, N s/m (``particle_ground``)."""
    if ground is None or not ground.on_particles:
        return np.zeros(3), 0.0
    s = vol0 ** (1.0 / 3.0)
    depth = ground.height + 0.5 * s - x[2]
    if depth <= 0:
        return np.zeros(3), 0.0
    inv_tau = k_mat[1] / s
    k = k_mat[0] * s
    f = np.array([0.0, 0.0, max(k * depth - 4.0 * ground.damping * m * inv_tau * v[2], 0.0)])
    speed = np.linalg.norm(v[:2])
    if ground.mode == "separate" and speed > 0:
        f[:2] = -min(ground.friction * f[2], friction_rate * m * speed * inv_tau) * v[:2] / speed
    return f, 2.0 * ground.rest_damping * np.sqrt(k * max(m, k * depth * inv_gravity))


def _contact_limits(scene, x, vol0, cfl) -> tuple[float, float, float]:
    """The resting dashpot's speed limit, 1 / |g| and the friction's rate (``pack_contact``)."""
    if scene.ground is None or not scene.ground.on_particles:
        return 0.0, 0.0, 1.0
    struct = pack_contact(scene.ground, scene.gravity, x, vol0, cfl)
    return struct.rest_speed, struct.inv_gravity, struct.friction_rate


def _grip(ground, m, v_free, vel):
    if ground is None or ground.mode != "separate" or ground.held_depth <= 0 or np.array_equal(vel, v_free):
        return 0.0
    used = m * np.linalg.norm((vel - v_free)[:2])
    return max(ground.friction * m * (vel[2] - v_free[2]) - used, 0.0)


def _surface_friction(ground, grid, gm, gv, gdv, grip):
    """The ground's tangential condition on the node layer above the held one (``surface_friction``)."""
    layer = None if ground is None else ground.surface_friction_layer(grid)
    if layer is None:
        return
    for i, j in np.ndindex(*grid.res[:2]):
        m, node = gm[i, j, layer + 1], (i, j, layer + 1)
        if m <= 0 or gm[i, j, layer] <= 0 or grip[i, j, layer] <= 0:
            continue
        sliding = m * np.linalg.norm(gv[node][:2])
        if sliding <= 0:
            continue
        keep = 0.0 if sliding <= grip[i, j, layer] else 1 - grip[i, j, layer] / sliding
        vel = np.array([keep * gv[node][0], keep * gv[node][1], gv[node][2]])
        gdv[node] += vel - gv[node]
        gv[node] = vel


def substep(
    state: dict, params: list, grid, scene, dt: float, t: float, flip: float, bound: int, cfl: float = 1.0
) -> dict:
    """One sub-step. ``state``: x [P,3], v [P,3], C [P,3,3], F [P,3,3], plastic [P], mass [P],
    vol0 [P], material [P]; ``params``: [M] MaterialParams; ``cfl``: the solver's, which sets the
    particle friction's cap (``particle_ground``). Returns the new state, ``grid_v`` and
    ``ground_impulse`` [3], N s: what the particle contact gave this sub-step (springs, friction
    and the resting dashpot)."""
    x, v, C, F = state["x"], state["v"], state["C"], state["F"]
    mass, vol0, material, plastic = state["mass"], state["vol0"], state["material"], state["plastic"]
    res, dx, origin = np.array(grid.res), grid.dx, np.asarray(grid.origin)
    n = len(x)
    ground = scene.ground
    raised = raised_modulus(params, vol0, material, scene.gravity, dx)
    ground_k = ground_stiffness(ground, params, raised).astype(np.float64)
    # Stress of the current (already projected) F.
    tau = np.zeros((n, 3, 3))
    for m, p in enumerate(params):
        sel = material == m
        if sel.any():
            tau[sel] = cref.update(p, F[sel], plastic[sel], 0.0)[1]
    mom = np.zeros((*res, 3))
    force = np.zeros((*res, 3))
    gm = np.zeros(tuple(res))
    gc = np.zeros(tuple(res))
    rest_speed, inv_gravity, friction_rate = _contact_limits(scene, x, vol0, cfl)
    ground_impulse = np.zeros(3)
    stencils = []
    for p in range(n):
        xp = (x[p] - origin) / dx
        base = np.clip((xp - 0.5).astype(int), 0, res - 3)
        fx = xp - base
        w = _weights(fx)
        stencils.append((base, fx, w))
        impulse = -dt * 4 / dx**2 * vol0[p] * tau[p]
        contact, c_rest = _particle_ground_force(
            ground, ground_k[material[p]], x[p], v[p], mass[p], vol0[p], inv_gravity, friction_rate
        )
        external = dt * contact
        ground_impulse += external
        affine = mass[p] * C[p] + impulse
        for o in np.ndindex(3, 3, 3):
            wi = w[o[0], 0] * w[o[1], 1] * w[o[2], 2]
            dpos = (np.array(o) - fx) * dx
            node = tuple(base + o)
            mom[node] += wi * (mass[p] * v[p] + affine @ dpos + external)
            force[node] += wi * (impulse @ dpos + external)
            gm[node] += wi * mass[p]
            gc[node] += wi * c_rest
    gv = np.zeros((*res, 3))
    gdv = np.zeros((*res, 3))
    grip = np.zeros(tuple(res))
    g = np.asarray(scene.gravity, float)
    for node in zip(*np.nonzero(gm >= NODE_MASS_FLOOR), strict=True):  # lighter nodes are empty
        m = gm[node]
        v_transfer = (mom[node] - force[node]) / m
        vel = mom[node] / m + dt * g
        pos = origin + np.array(node) * dx
        for box in scene.boxes:
            vel = _box_velocity(box, pos, t, vel)
        if gc[node] > 0 and -rest_speed < vel[2] < 0:
            vz = vel[2] * m / (m + dt * gc[node])
            ground_impulse[2] += m * (vz - vel[2])
            vel[2] = vz
        v_free = vel
        vel = _ground_velocity(scene.ground, pos, dx, vel)
        grip[node] = _grip(scene.ground, m, v_free, vel)
        for a in range(3):
            if (node[a] < bound and vel[a] < 0) or (node[a] >= res[a] - bound and vel[a] > 0):
                vel[a] = 0.0
        gv[node], gdv[node] = vel, vel - v_transfer
    _surface_friction(scene.ground, grid, gm, gv, gdv, grip)
    out = {k: np.array(val, dtype=np.float64, copy=True) for k, val in state.items()}
    out["grid_v"] = gv
    out["ground_impulse"] = ground_impulse
    for p in range(n):
        base, fx, w = stencils[p]
        vel, dvel, B, dB = np.zeros(3), np.zeros(3), np.zeros((3, 3)), np.zeros((3, 3))
        for o in np.ndindex(3, 3, 3):
            wi = w[o[0], 0] * w[o[1], 1] * w[o[2], 2]
            node = tuple(base + o)
            vel += wi * gv[node]
            dvel += wi * gdv[node]
            B += wi * np.outer(gv[node], np.array(o) - fx)
            dB += wi * np.outer(gdv[node], np.array(o) - fx)
        c_grid = 4 / dx * B
        v_new = vel + flip * (v[p] + dvel - vel)
        c_new = c_grid + flip * (C[p] + 4 / dx * dB - c_grid)
        v_move = vel  # particles move with the grid velocity; only v carries the FLIP share
        for box in (b for b in scene.boxes if b.carry):
            v_new = _box_velocity(box, x[p], t, v_new)
            v_move = _box_velocity(box, x[p], t, v_move)
        F_trial = (np.eye(3) + dt * c_grid) @ F[p]
        prm = params[material[p]]
        F_new, _, pl = cref.update(prm, F_trial[None], plastic[p : p + 1], dt)
        out["x"][p] = x[p] + dt * v_move
        out["v"][p], out["C"][p], out["F"][p] = v_new, c_new, F_new[0]
        if pl is not None:
            out["plastic"][p] = pl[0]
    return out
