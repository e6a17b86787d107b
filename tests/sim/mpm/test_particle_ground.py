"""The ground's particle contact (``particle_ground``): numpy twin, reported force, heavy bodies,
bodies that start on the plane, and the step the springs allow."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from physgm.bench.verification import analytic as V
from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm import kernels as K
from physgm.sim.mpm import reference_mpm
from physgm.sim.mpm.boundary import GroundPlane
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.solver import MPMSolver
from physgm.sim.mpm.state import Particles
from physgm.sim.mpm.stepping import SolverConfig, step_wave_speed, wave_speed

DX = 0.02
SP = DX / 2
JELLY = MaterialParams("fixed_corotated", 1e5, 0.3, 1000.0)


def _twin_state(solver: MPMSolver, p: Particles, density: float) -> dict:
    s0 = solver.state()
    state = {"x": s0.x, "v": s0.v, "C": s0.C, "F": s0.F, "plastic": s0.plastic}
    state["mass"] = density * p.volume
    state["vol0"] = p.volume
    state = {k: np.asarray(val, dtype=np.float64) for k, val in state.items()}
    state["material"] = p.material
    return state


@pytest.mark.parametrize(
    "mode, damping, speed",
    [("slip", 0.2, 2.0), ("separate", 0.0, 2.0), ("separate", 0.2, 2.0), ("separate", 0.2, 0.1)],
)
def test_contact_matches_the_numpy_twin_and_reports_its_force(mode, damping, speed):
    # A block hitting the plane at ``speed`` while sliding, its surface ``speed`` x 50 us above
    # it: four sub-steps against the twin; the contact acts (without it the bottom layer falls
    # on), and the ground impulse is the twin's, step by step. At 2 m/s (faster than the resting
    # dashpot's sqrt(g s) = 0.31 m/s) that dashpot takes almost nothing; at 0.1 m/s a share.
    gap = speed * 5e-5
    p = Particles.lattice((-0.02, -0.02, gap), (0.02, 0.02, gap + 0.03), SP)
    p.v = np.tile([0.5, 0.1, -speed], (len(p), 1))
    ground = GroundPlane(0.0, friction=0.4, mode=mode, contact="particles", damping=damping)
    scene = Scene(ground=ground)
    grid = GridSpec.fit((-0.05, -0.05, 0.0), (0.05, 0.05, 0.05), DX)
    solver = MPMSolver(p, [JELLY], grid, scene, SolverConfig(flip=0.0, threads=1))
    assert solver.launches.contact_height == 0.0  # nothing started under the plane
    state = _twin_state(solver, p, 1000.0)
    bound, cfl = SolverConfig().boundary_cells, SolverConfig().cfl
    k_mat = np.array([JELLY.mu, 0.5 * np.sqrt(JELLY.mu / 1000.0)])
    impulse, springs = np.zeros(3), np.zeros(3)
    for dt in (2e-4, 1.5e-4, 2e-4, 2e-4):
        for i in range(len(p)):
            f, _ = reference_mpm._particle_ground_force(
                scene.ground, k_mat, state["x"][i], state["v"][i], state["mass"][i], state["vol0"][i],
                friction_rate=1.0 / cfl,
            )  # fmt: skip
            springs += dt * f
        out = reference_mpm.substep(state, [JELLY], solver.grid, scene, dt, solver.time, 0.0, bound, cfl)
        impulse += out["ground_impulse"]
        solver.substep(dt)
        state.update({k: out[k] for k in ("x", "v", "C", "F", "plastic")})
        reported = solver.arrays.work.numpy().sum(0)[K.WORK_GROUND : K.WORK_GROUND + 3]
        np.testing.assert_allclose(reported, impulse, rtol=1e-4, atol=1e-9)
    assert impulse[2] > 0 and (impulse[0] < 0 if mode == "separate" else impulse[0] == 0)
    np.testing.assert_allclose(impulse[:2], springs[:2], rtol=1e-6)  # friction acts on the particles only
    if speed > 0.5:
        assert impulse[2] == pytest.approx(springs[2], rel=1e-4)  # the resting dashpot: ~nothing at impact
    else:
        assert impulse[2] > 1.1 * springs[2]  # the resting dashpot took a share of the stop
    s1 = solver.state()
    np.testing.assert_allclose(s1.v, state["v"], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(s1.x, state["x"], rtol=1e-6, atol=1e-6)
    low = s1.x[:, 2] < s1.x[:, 2].min() + 0.5 * SP  # the lowest layer of particles
    free = reference_mpm.substep(state, [JELLY], solver.grid, Scene(), 2e-4, solver.time, 0.0, bound, cfl)
    held = reference_mpm.substep(state, [JELLY], solver.grid, scene, 2e-4, solver.time, 0.0, bound, cfl)
    assert held["v"][low, 2].mean() > free["v"][low, 2].mean() + 0.025 * speed  # m/s, in one sub-step
    solver.close()


def test_heavy_sand_heap_on_a_coulomb_floor_does_not_sink():
    # The 13 cm sand cone of the sand-pile case (mohr_coulomb, 35 degrees, 1600 kg/m^3) on a
    # Coulomb floor instead of a sticky one: its lowest particles stay a quarter cell up, its
    # surface on the plane (the nodes held 7/8 cell down let the sticky heap sink 0.6 cell under).
    sp, radius, height = 0.006, 0.08, 0.13
    inside = lambda x: np.hypot(x[:, 0], x[:, 1]) < radius * (1 - x[:, 2] / height)  # noqa: E731
    p = Particles.lattice((-radius, -radius, 0.0), (radius, radius, height), sp, inside=inside)
    sand = MaterialParams("mohr_coulomb", 3.5e5, 0.3, 1600.0, friction_angle=35.0)
    reach = radius + 2 * height
    scene = Scene(ground=GroundPlane(0.0, friction=0.5, contact="particles"), damping=20.0)
    solver = V._solver(p, sand, (-reach, -reach, 0.0), (reach, reach, height), 2 * sp, scene)
    for _ in range(15):
        solver.step_frame()
    low = float(solver.state().x[:, 2].min()) / (2 * sp)
    solver.close()
    assert low == pytest.approx(0.25, abs=0.02), low  # measured 0.245 dx after 1 s


SOFT = MaterialParams("fixed_corotated", 2e3, 0.45, 1000.0)  # a jelly about as soft as its weight


def _soft_cube(speed: float) -> MPMSolver:
    """A 10 cm cube of SOFT, 1,000 particles, on a Coulomb floor or, moving down, 1 cm above it."""
    lift = 0.01 if speed > 0 else 0.0
    p = Particles.lattice((-0.05, -0.05, lift), (0.05, 0.05, 0.1 + lift), SP)
    p = replace(p, v=np.tile(np.float32([0.0, 0.0, -speed]), (len(p), 1)))
    grid = GridSpec.fit((-0.2, -0.2, 0.0), (0.2, 0.2, 0.22), DX)
    scene = Scene(ground=GroundPlane(0.0, friction=0.3, contact="particles"))
    return MPMSolver(p, [SOFT], grid, scene, SolverConfig(threads=1, frame_dt=0.005))


M_SOFT = SOFT.lam + 2 * SOFT.mu  # 7,586 Pa


@pytest.mark.parametrize(
    "material, dx, expected",
    [(SOFT, DX, M_SOFT), (JELLY, DX, JELLY.mu), (SOFT, 0.026, M_SOFT * (2 * SP / 0.026) ** 2)],
)
def test_the_spring_under_a_body_as_soft_as_its_weight_is_raised_to_its_load(material, dx, expected):
    # W = rho g V^(1/3) = 981 Pa under the 10 cm cube: 8 W = 7,848 Pa lies above G = 690 Pa and is
    # capped at M = 7,586 Pa; the 1e5 Pa jelly's G = 38,462 Pa is already above 8 W. On a cell 2.6
    # spacings wide the spring stops at M (2 s / dx)^2 = 4,489 Pa, where it rings as fast as the
    # P-wave crosses a cell, so the step is the material's own.
    assert SOFT.mu < 8 * 1000.0 * 9.81 * 0.1 < JELLY.mu
    p = Particles.lattice((-0.05, -0.05, 0.01), (0.05, 0.05, 0.11), SP)
    scene = Scene(ground=GroundPlane(0.0, contact="particles"))
    grid = GridSpec.fit((-0.2, -0.2, 0.0), (0.2, 0.2, 0.22), dx)
    solver = MPMSolver(p, [material], grid, scene, SolverConfig(threads=1))
    k = solver.launches.ground_k.numpy()[0]
    solver.close()
    assert k[0] == pytest.approx(expected, rel=1e-5)
    assert k[1] == pytest.approx(0.5 * np.sqrt(expected / material.density), rel=1e-5)
    assert step_wave_speed([material], scene, p, dx) == pytest.approx(wave_speed([material]), rel=1e-6)


@pytest.mark.parametrize("speed, deepest", [(0.0, 0.4), (3.0, 1.6)])
def test_a_body_as_soft_as_its_weight_rests_and_lands_on_the_plane(speed, deepest):
    # Its surface's deepest point under the plane over 0.3 s, in spacings: set down and sagging
    # under its weight, 0.31 (1.57 with the spring at G); thrown down at 3 m/s, faster than its
    # P-wave (2.8 m/s), 1.22 (3.74 at G).
    solver = _soft_cube(speed)
    depth = []
    for _ in range(60):
        solver.step_frame()
        depth.append((SP / 2 - float(solver.state().x[:, 2].min())) / SP)
    solver.close()
    assert max(depth) < deepest, depth


def test_body_placed_with_its_particles_on_the_plane_stays_down():
    # Scenes put the lowest particle centres on the floor (half a spacing of overlap): the springs
    # push from a plane lowered by that overlap, so a stiff block neither jumps nor sinks.
    p = Particles.lattice((-0.04, -0.04, -SP / 2), (0.04, 0.04, 0.05 - SP / 2), SP)
    wood = MaterialParams("fixed_corotated", 5e6, 0.3, 600.0)
    grid = GridSpec.fit((-0.08, -0.08, 0.0), (0.08, 0.08, 0.1), DX)
    scene = Scene(ground=GroundPlane(0.0, friction=0.3, contact="particles"))
    solver = MPMSolver(p, [wood], grid, scene, SolverConfig(threads=1))
    assert solver.launches.contact_height == pytest.approx(-SP / 2, abs=1e-6)
    top = []
    for _ in range(5):
        solver.step_frame()
        top.append(float(solver.state().x[:, 2].max()))
    solver.close()
    assert max(top) - p.x[:, 2].max() < 0.01 * DX  # without the lowered plane it jumped 8 cm


def test_step_allows_for_the_springs_only_when_they_need_it():
    # omega dt <= 2 cfl needs c >= c_X dx / (2 s): with 2 particles per cell axis the material's
    # own c_p already covers it; 4 per axis halve s and need c_X dx / (2 s) = 2 c_X.
    ground = GroundPlane(0.0, contact="particles")
    for per_axis, expected in [(2, wave_speed([JELLY])), (4, 2.0 * np.sqrt(JELLY.mu / 1000.0))]:
        s = DX / per_axis
        p = Particles.lattice((0.0, 0.0, 0.0), (0.04, 0.04, 0.04), s)
        speed = step_wave_speed([JELLY], Scene(ground=ground), p, DX)
        assert speed == pytest.approx(max(expected, wave_speed([JELLY])))
    nodes = replace(ground, contact="nodes")
    assert step_wave_speed([JELLY], Scene(ground=nodes), p, DX) == wave_speed([JELLY])
    with pytest.raises(ValueError, match="contact='nodes'"):
        GroundPlane(0.0, mode="sticky", contact="particles")
