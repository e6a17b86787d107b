"""Rigid path against analytic mechanics: free fall, restitution, Coulomb sliding, torque-free spin."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from physgm.sim.rigid import ContactParams, RigidBody, RigidSimulator

G = 9.81


def _cube(half: float = 0.05, center=(0.0, 0.0, 0.05), n: int = 9) -> tuple[np.ndarray, np.ndarray]:
    g = np.linspace(-half, half, n)
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + np.asarray(center)
    mass = np.full(len(x), 7850 * (2 * half) ** 3 / len(x))  # steel
    return x, mass


def _sim(x, mass, v, **contact) -> RigidSimulator:
    body = RigidBody.from_particles(x, mass)
    return RigidSimulator(body, ContactParams(**contact), RigidSimulator.initial_state(body, x, mass, v))


def test_inertia_of_cube_matches_formula():
    x, mass = _cube(n=21)
    body = RigidBody.from_particles(x, mass)
    # Lattice linspace(-h, h, n) per axis: mean of coordinate^2 is h^2 (n + 1) / (3 (n - 1)) exactly,
    # and I_xx = m (<y^2> + <z^2>) (the continuum limit is m a^2 / 6).
    second_moment = 0.05**2 * 22 / (3 * 20)
    np.testing.assert_allclose(np.diag(body.inertia), body.mass * 2 * second_moment, rtol=1e-6)
    np.testing.assert_allclose(body.inertia - np.diag(np.diag(body.inertia)), 0, atol=1e-12)
    assert len(body.points) == 8  # the cube's corners are its hull


def test_free_fall_follows_gravity():
    x, mass = _cube(center=(0, 0, 2.0))
    sim = _sim(x, mass, np.zeros_like(x), ground_height=0.0)
    traj = sim.run(n_frames=11, frame_dt=0.04, dt=1e-3)
    t = np.arange(11) * 0.04
    # Semi-implicit Euler: z = z0 - g t (t + dt) / 2, within dt of the exact -g t^2 / 2.
    np.testing.assert_allclose(traj.coms[:, 2], 2.0 - 0.5 * G * t**2, atol=G * 0.4 * 1e-3)
    np.testing.assert_allclose(traj.velocities[:, 2], -G * t, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("restitution", [0.3, 0.8])
def test_bounce_rebound_ratio_is_restitution(restitution):
    x, mass = _cube(center=(0, 0, 0.55))  # bottom face 0.5 m above the ground
    sim = _sim(x, mass, np.zeros_like(x), restitution=restitution, friction=0.3)
    traj = sim.run(n_frames=20, frame_dt=0.04, dt=2e-3)  # a coarse step: the time of impact is found
    t_hit, vn_in, vn_out = traj.events[0]
    assert vn_in == pytest.approx(-math.sqrt(2 * G * 0.5), rel=5e-3)
    assert t_hit == pytest.approx(math.sqrt(2 * 0.5 / G), abs=2e-3)
    assert vn_out / -vn_in == pytest.approx(restitution, rel=0.05)
    # The rebound apex is e^2 times the drop height (within a few mm).
    apex = traj.coms[:, 2][int(t_hit / 0.04) + 1 :].max() - 0.05
    assert apex == pytest.approx(restitution**2 * 0.5, abs=0.01)


@pytest.mark.parametrize("mu", [0.2, 0.5])
def test_friction_stops_sliding_at_coulomb_distance(mu):
    x, mass = _cube()
    v = np.zeros_like(x)
    v[:, 0] = 2.0
    sim = _sim(x, mass, v, friction=mu, restitution=0.5)
    traj = sim.run(n_frames=40, frame_dt=0.04, dt=1e-3)
    distance = traj.coms[-1, 0] - traj.coms[0, 0]
    assert distance == pytest.approx(2.0**2 / (2 * mu * G), rel=0.05)
    assert np.abs(traj.omegas).max() < 1e-6  # slides flat, no tipping at these speeds
    assert traj.coms[-1, 2] == pytest.approx(0.05, abs=1e-6)


def test_angular_momentum_conserved_and_rotation_matches_euler_equations():
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (3000, 3)) * [0.1, 0.05, 0.02] + [0, 0, 1]
    mass = np.full(len(x), 1e-3)
    body = RigidBody.from_particles(x, mass)
    omega0 = np.array([0.1, 5.0, 0.1])  # close to the unstable intermediate axis: tumbles
    v = np.cross(omega0, x - body.com) + [0.5, 0.0, 3.0]
    sim = RigidSimulator(
        body, ContactParams(ground_height=None), RigidSimulator.initial_state(body, x, mass, v)
    )
    L0 = sim.state.L.copy()
    e_rot0 = 0.5 * L0 @ sim.omega()
    traj = sim.run(n_frames=51, frame_dt=0.04, dt=1e-3)
    np.testing.assert_allclose(sim.state.L, L0, rtol=1e-12)
    assert 0.5 * sim.state.L @ sim.omega() == pytest.approx(e_rot0, rel=1e-3)
    inv_inertia = np.linalg.inv(body.inertia)

    def rhs(_t, y):
        rot = y.reshape(3, 3)
        w = rot @ inv_inertia @ rot.T @ L0
        skew = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        return (skew @ rot).ravel()

    ref = solve_ivp(rhs, [0, 2.0], np.eye(3).ravel(), rtol=1e-10, atol=1e-12).y[:, -1].reshape(3, 3)
    np.testing.assert_allclose(traj.rotations[-1], ref, atol=1e-3)
    # Centre of mass is a parabola, untouched by the spin.
    np.testing.assert_allclose(traj.coms[-1, :2], body.com[:2] + [0.5 * 2.0, 0.0], atol=1e-9)


def test_tilted_drop_comes_to_rest_on_a_face_and_is_held():
    from scipy.spatial.transform import Rotation

    x, mass = _cube(center=(0, 0, 0))
    x = x @ Rotation.from_euler("xyz", [20, 35, 10], degrees=True).as_matrix().T + [0, 0, 0.4]
    sim = _sim(x, mass, np.zeros_like(x), restitution=0.4, friction=0.5)
    traj = sim.run(n_frames=75, frame_dt=0.04, dt=1e-3, rest_speed=0.01)
    assert traj.rest_frame is not None and traj.rest_frame < 75
    final = traj.transform(x, -1)
    assert final[:, 2].min() == pytest.approx(0.0, abs=1e-4)
    assert final[:, 2].max() == pytest.approx(0.1, abs=2e-3)  # flat on a face
    np.testing.assert_array_equal(
        traj.coms[traj.rest_frame :], np.broadcast_to(traj.coms[-1], traj.coms[traj.rest_frame :].shape)
    )


@pytest.mark.parametrize("restitution", [0.0, 0.6])
def test_throw_at_a_wall_rebounds_with_restitution(restitution):
    # No gravity, no ground: a cube thrown at 2 m/s along x into the plane x = 0.3 (normal -x).
    x, mass = _cube(center=(0.0, 0.0, 0.0))
    v = np.tile([2.0, 0.0, 0.0], (len(x), 1))
    sim = _sim(
        x,
        mass,
        v,
        ground_height=None,
        walls=(((-1.0, 0.0, 0.0), -0.3),),
        gravity=(0.0, 0.0, 0.0),
        restitution=restitution,
    )
    traj = sim.run(n_frames=16, frame_dt=0.04, dt=1e-3)
    assert np.all(traj.coms[:, 0] + 0.05 <= 0.3 + 1e-6)  # the front face never passes the wall
    np.testing.assert_allclose(traj.velocities[-1], [-2.0 * restitution, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(traj.omegas[-1], 0.0, atol=1e-6)  # a face-on hit does not spin it
    # Contact at t = 0.125 s (0.25 m to go): the first frames are free flight.
    np.testing.assert_allclose(traj.coms[:4, 0], 2.0 * np.arange(4) * 0.04, atol=1e-9)


def test_static_walls_from_scene_boxes():
    from physgm.sim.mpm.boundary import VelocityBox
    from physgm.sim.rigid import static_walls

    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([0.1, 0.1, 0.1])
    wall = VelocityBox((0.15, -1.0, -1.0), (0.2, 1.0, 1.0))
    assert static_walls((wall,), lo, hi) == [((-1.0, 0.0, 0.0), -0.15)]
    behind = VelocityBox((-0.2, -1.0, -1.0), (-0.05, 1.0, 1.0))
    assert static_walls((behind,), lo, hi) == [((1.0, 0.0, 0.0), -0.05)]
    clamp = VelocityBox((-0.1, -0.1, 0.05), (0.2, 0.2, 0.2))  # overlaps the object
    grip = VelocityBox((0.15, -1.0, -1.0), (0.2, 1.0, 1.0), velocity=(0.1, 0.0, 0.0))
    assert static_walls((clamp,), lo, hi) is None and static_walls((wall, grip), lo, hi) is None
    assert static_walls((), lo, hi) == []


def test_sliding_on_the_ground_into_a_wall_bounces_at_the_wall():
    # Resting on the ground (touching it) while sliding at 2 m/s into the wall x = 0.3: the step
    # is still cut at the wall, so the rebound starts at the wall, not a step's travel inside it.
    # No gravity, so the cube keeps touching the ground instead of hopping.
    x, mass = _cube(center=(0.0, 0.0, 0.05))
    v = np.tile([2.0, 0.0, 0.0], (len(x), 1))
    sim = _sim(
        x,
        mass,
        v,
        ground_height=0.0,
        friction=0.0,
        restitution=1.0,
        gravity=(0.0, 0.0, 0.0),
        walls=(((-1.0, 0.0, 0.0), -0.3),),
    )
    traj = sim.run(n_frames=6, frame_dt=0.04, dt=7e-3)  # coarse steps: 14 mm of travel each
    assert np.all(traj.coms[:, 0] + 0.05 <= 0.3 + 1e-6)
    # Elastic and frictionless: at t = 0.2 s it went 0.25 m out and 0.15 m back.
    assert traj.coms[5, 0] == pytest.approx(0.1, abs=1e-6)


def _cylinder(tilt_deg: float, radius: float = 0.05, height: float = 0.2, drop: float = 0.1):
    """A solid cylinder (particles inside plus its two rims), tilted about y, lowest point at drop."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    r, th = radius * np.sqrt(rng.random(4000)), 2 * np.pi * rng.random(4000)
    inside = np.stack([r * np.cos(th), r * np.sin(th), height * rng.random(4000)], 1)
    a = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    rims = [np.stack([radius * np.cos(a), radius * np.sin(a), np.full(64, z)], 1) for z in (0.0, height)]
    x = np.concatenate([inside, *rims]) @ Rotation.from_euler("y", tilt_deg, degrees=True).as_matrix().T
    x[:, 2] += drop - x[:, 2].min()
    return x, np.full(len(x), 1.0 / len(x))


@pytest.mark.parametrize("tilt", [0.0, 0.5, 1.0])
def test_a_can_that_lands_almost_flat_rebounds_flat_and_stays_upright(tilt):
    # A 10 cm wide, 20 cm tall cylinder dropped 10 cm on its base (1.4 m/s). 1 degree off level,
    # its far rim lands 1.7 mm, 1.2 ms after the near one: one impact in practice. Each rim point
    # asked for its own rebound speed in turn, the near rim's impulse alone spun the can, and it
    # toppled at 0.5 and 1 degree; landing exactly flat, the impulse shared among the base's
    # points in the sweep's order tilted it by 7 degrees.
    x, mass = _cylinder(tilt)
    sim = _sim(x, mass, np.zeros_like(x), restitution=0.6, friction=0.3)
    traj = sim.run(n_frames=50, frame_dt=0.04, dt=1e-3)
    axis = traj.rotations @ x[-1] - traj.rotations @ x[-65]  # a top-rim point minus a bottom-rim one
    tilts = np.degrees(np.arccos(np.abs(axis[:, 2]) / np.linalg.norm(axis, axis=1)))
    assert tilts.max() <= tilt + 0.5
    assert tilts[-1] <= 0.5
    t_hit, vn_in, vn_out = traj.events[0]
    assert vn_out / -vn_in == pytest.approx(0.6, rel=0.05)


def test_a_rod_landing_on_one_end_rebounds_at_the_restitution_speed():
    # A 20 cm rod, 1 cm square, at 45 degrees lands on its lower edge at 0.5 m/s, frictionless:
    # the edge's normal speed reverses at the restitution, and the impulse is the textbook one.
    from scipy.spatial.transform import Rotation

    g = np.linspace(-0.5, 0.5, 5)
    x = np.stack(np.meshgrid(np.linspace(-0.1, 0.1, 81), 0.01 * g, 0.01 * g, indexing="ij"), -1)
    x = x.reshape(-1, 3) @ Rotation.from_euler("y", 45, degrees=True).as_matrix().T + [0, 0, 0.1]
    mass = np.full(len(x), 1e-3)
    v = np.tile([0.0, 0.0, -0.5], (len(x), 1))
    sim = _sim(x, mass, v, restitution=0.5, friction=0.0, gravity=(0, 0, 0))
    sim.run(n_frames=4, frame_dt=0.04, dt=1e-3)
    t_hit, vn_in, vn_out = sim.events[0]
    assert vn_in == pytest.approx(-0.5, rel=1e-9)
    assert vn_out == pytest.approx(0.25, rel=1e-6)
    # J = (1 + e) m v / (1 + m r^2 / I): r the edge's horizontal arm, I about the edge's direction.
    body = sim.body
    arm = body.points[np.argmin(body.points[:, 2]), 0]
    impulse = 1.5 * body.mass * 0.5 / (1 + body.mass * arm**2 / body.inertia[1, 1])
    assert sim.state.v[2] == pytest.approx(-0.5 + impulse / body.mass, rel=1e-6)


@pytest.mark.parametrize("speed", [10.0, 30.0])
def test_a_fast_landing_on_a_corner_spins_as_on_that_corner(speed):
    # A 10 cm cube tilted 10 and 5 degrees lands on one corner; its neighbours are 9 and 17 mm up.
    # A millisecond at 10 or 30 m/s reaches 10 or 30 mm: with no limit (impact_reach = 1) it lands
    # on an edge (89 rad/s against the corner's 24) or flat (2.2 against 71). A faster impact is
    # shorter, and the window stops at 2 % of the body's size, so the spin is the single corner's
    # (impact_time = 0).
    from scipy.spatial.transform import Rotation

    x, mass = _cube(center=(0.0, 0.0, 0.0))
    x = x @ Rotation.from_euler("xyz", [10, 5, 0], degrees=True).as_matrix().T
    x[:, 2] += 0.05 - x[:, 2].min()
    v = np.tile([0.0, 0.0, -speed], (len(x), 1))
    spins = []
    for impact_time in (0.0, 1e-3):
        sim = _sim(x, mass, v, restitution=0.6, friction=0.3, gravity=(0, 0, 0), impact_time=impact_time)
        sim.run(n_frames=3, frame_dt=0.005, dt=1e-4)
        spins.append(sim.omega())
    assert np.linalg.norm(spins[0]) > 0.7 * speed  # the corner's impulse spins it hard
    np.testing.assert_allclose(spins[1], spins[0], rtol=1e-6, atol=1e-9)
