"""Flights between contacts in closed form (``physgm.sim.coast``): against the exact rigid motion,
and a bouncing rubber cube against the explicit MPM it replaces."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from physgm.physics.materials import get_material
from physgm.sim.coast import STEPS_PER_FRAME, coast, next_flight, vibration
from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm.boundary import GroundPlane
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.state import ParticleState

G = np.array([0.0, 0.0, -9.81])
FRAME_DT = 1.0 / 24.0


def _cube(side: float = 0.1, n: int = 6, centre=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """A lattice cube of n^3 particles (uniform mass: its inertia is isotropic)."""
    axis = (np.arange(n) + 0.5) / n * side - side / 2
    x = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) + np.asarray(centre)
    return x, np.full(len(x), 0.01)


def _rigid_velocities(x: np.ndarray, v_com: np.ndarray, omega: np.ndarray) -> np.ndarray:
    return v_com + np.cross(omega, x - x.mean(0))


def test_a_spinning_cube_flies_the_exact_rigid_motion():
    """Isotropic inertia: constant spin, so frame k is the take-off pose turned by omega k dt and
    moved along the parabola."""
    x, m = _cube()
    v_com, omega = np.array([0.3, -0.2, 1.5]), np.array([2.0, -1.0, 3.0])
    v = _rigid_velocities(x, v_com, omega)
    F = np.tile(np.eye(3), (len(x), 1, 1))
    C = np.zeros((len(x), 3, 3))
    flight = coast(x, v, F, C, m, 0.0, G, FRAME_DT, max_frames=5, gap=0.05)
    assert flight is not None and flight.frames == 5
    com0 = x.mean(0)
    for k in range(5):
        t = (k + 1) * FRAME_DT
        R = Rotation.from_rotvec(omega * t).as_matrix()
        expect = (x - com0) @ R.T + com0 + v_com * t + 0.5 * G * t * t
        np.testing.assert_allclose(flight.x[k], expect, atol=2e-6)
        np.testing.assert_allclose(flight.F[k], np.broadcast_to(R, F.shape), atol=2e-6)
    t = 5 * FRAME_DT
    np.testing.assert_allclose(
        flight.v, _rigid_velocities(flight.x[-1].astype(np.float64), v_com + G * t, omega), atol=1e-5
    )
    # The spin's velocity gradient is the skew matrix of omega, before and after.
    skew = np.array([[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]], [-omega[1], omega[0], 0.0]])
    C0 = np.broadcast_to(skew, C.shape)
    again = coast(x, v, F, C0, m, 0.0, G, FRAME_DT, max_frames=5, gap=0.05)
    np.testing.assert_allclose(again.C, C0, atol=1e-6)


def test_the_vibration_and_deformation_are_carried_in_the_body_frame():
    """A velocity relative to the rigid motion and a stretch F come out turned with the body."""
    x, m = _cube()
    omega = np.array([0.0, 0.0, 4.0])
    # Vertical, even in x: no net momentum and no angular momentum, so the spin stays about z.
    wobble = 0.05 * np.cos(40.0 * (x[:, :1] - x[:, :1].mean())) * np.array([0.0, 0.0, 1.0])
    wobble -= wobble.mean(0)
    v = _rigid_velocities(x, np.zeros(3), omega) + wobble
    F = np.tile(np.diag([1.02, 0.99, 1.0]), (len(x), 1, 1))
    flight = coast(x, v, F, np.zeros((len(x), 3, 3)), m, 0.0, G, FRAME_DT, max_frames=3, gap=0.05)
    t = 3 * FRAME_DT
    R = Rotation.from_rotvec(omega * t).as_matrix()  # about z, the wobble's direction is kept
    np.testing.assert_allclose(flight.F[-1], np.broadcast_to(R @ F[0], F.shape), atol=2e-6)
    spin = _rigid_velocities(flight.x[-1].astype(np.float64), flight.v.mean(0), omega)
    np.testing.assert_allclose(flight.v - spin, wobble @ R.T, atol=1e-5)


def test_it_stops_before_the_lowest_point_comes_within_the_gap():
    x, m = _cube(centre=(0.0, 0.0, 0.3))
    v = np.tile([0.0, 0.0, 1.0], (len(x), 1))
    F = np.tile(np.eye(3), (len(x), 1, 1))
    gap = 0.03
    flight = coast(x, v, F, np.zeros((len(x), 3, 3)), m, 0.0, G, FRAME_DT, max_frames=100, gap=gap)
    assert flight is not None
    low = x[:, 2].min()
    # The last frame before the bottom falls to the gap, in closed form.
    t_hit = (1.0 + math.sqrt(1.0 + 2 * 9.81 * (low - gap))) / 9.81
    assert flight.frames == math.floor(t_hit / FRAME_DT)
    assert flight.x[:, :, 2].min() > gap
    # Below the gap already, or falling into it within a frame: nothing to coast.
    assert coast(x - [0, 0, 0.28], v, F, np.zeros_like(F), m, 0.0, G, FRAME_DT, 10, gap) is None
    falling = np.tile([0.0, 0.0, -5.0], (len(x), 1))
    near = x - [0, 0, 0.2]
    assert coast(near, falling, F, np.zeros_like(F), m, 0.0, G, FRAME_DT, 10, gap) is None
    assert STEPS_PER_FRAME >= 8  # the lowest point is looked at often enough not to skip the gap


def test_vibration_is_zero_for_rigid_motion_and_grows_with_the_wobble():
    x, m = _cube()
    vol = m / 1000.0
    rubber = get_material("rubber").params()
    omega = np.array([1.0, 2.0, -0.5])
    R = Rotation.from_rotvec([0.3, 0.1, 0.0]).as_matrix()
    v = _rigid_velocities(x, np.array([0.0, 0.0, 2.0]), omega)
    F = np.broadcast_to(R, (len(x), 3, 3))
    rigid = vibration(x, v, F, m, vol, rubber)
    assert rigid.amplitude < 1e-9 and rigid.rebound_speed < 1e-6
    # Two particles of mass m0 with relative speed +-u: RMS speed u sqrt(2 m0 / M), which rings with
    # amplitude (RMS speed) / omega_1, omega_1 = pi c_s / size; kinetic energy m0 u^2.
    u, m0, M = 0.01, m[0], m.sum()
    wobble = np.zeros_like(v)
    wobble[0, 2], wobble[1, 2] = u, -u
    size = float(np.ptp(x, axis=0).max())
    omega_1 = math.pi * math.sqrt(rubber.mu / rubber.density) / size
    shaken = vibration(x, v + wobble, F, m, vol, rubber)
    assert shaken.amplitude == pytest.approx(u * math.sqrt(2 * m0 / M) / omega_1, rel=1e-3)
    assert shaken.rebound_speed == pytest.approx(math.sqrt(2 * m0 * u * u / M), rel=1e-3)
    # A uniform stretch e along x: Green strain e + e^2 / 2, displacing by size x strain / 2, and the
    # elastic energy (mu + lam / 2) strain^2 per volume.
    e = 1e-3
    stretched = np.tile(np.diag([1.0 + e, 1.0, 1.0]), (len(x), 1, 1))
    strain = e + 0.5 * e * e
    still = vibration(x, v, stretched, m, vol, rubber)
    assert still.amplitude == pytest.approx(0.5 * size * strain, rel=1e-3)
    energy = vol.sum() * (rubber.mu + 0.5 * rubber.lam) * strain * strain
    assert still.rebound_speed == pytest.approx(math.sqrt(2 * energy / M), rel=1e-3)
    water = MaterialParams("fluid", E=2e6, nu=0.3, density=1000.0)
    assert vibration(x, v, F, m, vol, water).amplitude == math.inf


def test_next_flight_weighs_the_rebound_against_the_clip_left_after_the_flight():
    """The same vibrating body in the air: coasted when the clip ends in flight; refused when an
    impact follows with most of the clip still to come (the vibration's energy could change the
    rebound), or when it sits within the gap of the ground."""
    x, m = _cube(centre=(0.0, 0.0, 0.4))
    wobble = np.zeros_like(x)
    wobble[:, 2] = 0.02 * np.cos(40.0 * (x[:, 0] - x[:, 0].mean()))
    wobble -= wobble.mean(0)
    v = np.tile([0.0, 0.0, 1.0], (len(x), 1)) + wobble
    F = np.tile(np.eye(3), (len(x), 1, 1))
    state = ParticleState(x, v, F, np.zeros_like(F), np.zeros(len(x)), np.zeros(len(x), bool))
    rubber = get_material("rubber").params(E=1e6)
    scene = Scene(ground=GroundPlane(0.0))
    args = dict(frame_dt=FRAME_DT, gap=0.02, px_per_m=500.0, budget_px=0.5)
    vib = vibration(x, v, F, m, m / 1000.0, rubber)
    flight_frames = coast(x, v, F, np.zeros_like(F), m, 0.0, G, FRAME_DT, 100, 0.02).frames
    at_the_end = next_flight(state, m, m / 1000.0, rubber, scene, frames_left=flight_frames, **args)
    assert at_the_end is not None and at_the_end.frames == flight_frames
    assert at_the_end.predicted_px == pytest.approx(500.0 * vib.amplitude)
    # With 30 frames after the flight, the rebound term alone is far over the bound.
    assert 500.0 * 0.5 * vib.rebound_speed * 30 * FRAME_DT > 0.5
    assert next_flight(state, m, m / 1000.0, rubber, scene, frames_left=flight_frames + 30, **args) is None
    low = ParticleState(x - [0, 0, 0.34], v, F, np.zeros_like(F), np.zeros(len(x)), np.zeros(len(x), bool))
    assert next_flight(low, m, m / 1000.0, rubber, scene, frames_left=5, **args) is None
