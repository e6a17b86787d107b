"""Side walls, periodic axes, grid-face contact counts and the per-sub-step observables."""

from __future__ import annotations

import numpy as np
import pytest

from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm import GridSpec, GroundPlane, MPMSolver, Particles, Scene, SolverConfig
from physgm.sim.mpm.observables import ObservableRecorder
from physgm.sim.mpm.walls import PeriodicAxis, SideWall

SP = 0.0125
DX = 2 * SP
JELLY = MaterialParams("fixed_corotated", 1e5, 0.3, 1000.0)


def block(lo=(0.05, 0.05, 0.05), hi=(0.15, 0.15, 0.15), v=(0.0, 0.0, 0.0)) -> Particles:
    p = Particles.lattice(lo, hi, SP)
    p.v = np.tile(v, (len(p), 1))
    return p


def test_slip_and_sticky_walls_stop_the_normal_motion_and_report_their_force():
    results = {}
    for mode in ("slip", "sticky"):
        p = block(v=(-1.0, 0.5, 0.0))  # thrown at the wall x = 0, sliding along y
        wall = SideWall(axis=0, position=0.0, solid="below", mode=mode)
        grid = GridSpec.fit((-0.1, -0.1, -0.1), (0.4, 0.4, 0.25), DX)
        solver = MPMSolver(
            p, [JELLY], grid, Scene(gravity=(0, 0, 0), walls=(wall,)), SolverConfig(frame_dt=0.02)
        )
        rec = ObservableRecorder()
        solver.observers.append(rec)
        for _ in range(8):
            solver.step_frame()
        s = solver.state()
        obs = rec.arrays()
        results[mode] = s
        assert s.x[:, 0].min() > -DX  # held at the wall (node-based condition: within a cell)
        assert solver.face_contacts == 0
        # The wall pushed back along +x: its impulse is the momentum it took, M * 1 m/s at most ...
        mass = obs["mass"][0]
        impulse = (obs["wall_force"] * obs["dt"][:, None]).sum(0)
        assert 0.3 * mass < impulse[0] < 2.1 * mass
        # ... and the momentum balance closes: no gravity, no ground, only the wall.
        np.testing.assert_allclose(
            obs["momentum"][-1] - p.v.sum(0) * mass / len(p), impulse, atol=0.02 * mass
        )
    assert results["slip"].v[:, 1].mean() == pytest.approx(0.5, abs=0.05)  # slides on
    assert abs(results["sticky"].v[:, 1].mean()) < 0.35  # the sticky wall held the contact layer


def test_grid_face_contacts_are_counted_and_reported():
    p = block(v=(0.0, 0.0, 3.0))  # thrown at the top face, no ground, no gravity
    grid = GridSpec.fit((0.0, 0.0, 0.0), (0.2, 0.2, 0.2), DX)
    solver = MPMSolver(p, [JELLY], grid, Scene(gravity=(0, 0, 0)), SolverConfig(frame_dt=0.02))
    rec = ObservableRecorder()
    solver.observers.append(rec)
    stats = [solver.step_frame() for _ in range(6)]
    assert stats[0].face_contacts == 0 and stats[-1].face_contacts == solver.face_contacts > 0
    obs = rec.arrays()
    assert obs["face_contacts"].sum() == solver.face_contacts
    assert (obs["face_force"][:, 2] * obs["dt"]).sum() < 0  # the top face pushed down


def test_observables_of_a_resting_block_and_free_fall():
    p = block((-0.05, -0.05, 0.0), (0.05, 0.05, 0.1))
    grid = GridSpec.fit((-0.1, -0.1, 0.0), (0.1, 0.1, 0.15), DX)
    scene = Scene(ground=GroundPlane(0.0, friction=0.5))
    solver = MPMSolver(p, [MaterialParams("fixed_corotated", 2e5, 0.3, 1000.0)], grid, scene)
    rec = ObservableRecorder()
    solver.observers.append(rec)
    for _ in range(10):
        solver.step_frame()
    obs = rec.arrays()
    weight = obs["mass"][0] * 9.81
    late = obs["time"] > 0.2
    assert obs["ground_force"][late, 2].mean() == pytest.approx(weight, rel=0.03)
    np.testing.assert_allclose(obs["com_velocity"], obs["momentum"] / obs["mass"][:, None])
    # Free fall: the centre of mass gains g dt per sub-step and no boundary acts.
    q = block()
    solver = MPMSolver(q, [JELLY], GridSpec.fit((0.0, 0.0, -0.3), (0.2, 0.2, 0.2), DX), Scene())
    rec = ObservableRecorder()
    solver.observers.append(rec)
    solver.step_frame()
    obs = rec.arrays()
    np.testing.assert_allclose(obs["com_velocity"][:, 2], -9.81 * obs["time"], rtol=1e-4)
    assert not obs["ground_force"].any() and not obs["wall_force"].any() and not obs["face_force"].any()


def test_periodic_axis_wraps_particles_and_keeps_a_uniform_flow_uniform():
    """A layer filling the periodic period in y slides along y: it must stay exactly unstrained.

    Without the fold, the nodes at the period's ends would see half the mass and the layer's
    stress would spike there.
    """
    lo, hi = 0.0, 6 * DX
    p = block((0.05, lo, 0.05), (0.15, hi, 0.15), v=(0.0, 1.5, 0.0))
    grid = GridSpec((-0.1, lo - 6 * DX, -0.1), DX, (17, 6 + 13, 17))
    scene = Scene(gravity=(0, 0, 0), periodic=(PeriodicAxis(1, lo, hi),))
    solver = MPMSolver(p, [JELLY], grid, scene, SolverConfig(frame_dt=0.02))
    for _ in range(5):  # 0.1 s: the layer travels 0.15 m, a full period (0.15 m)
        solver.step_frame()
    s = solver.state()
    assert np.all((s.x[:, 1] >= lo) & (s.x[:, 1] < hi))
    np.testing.assert_allclose(s.v[:, 1], 1.5, atol=1e-3)
    np.testing.assert_allclose(np.linalg.det(s.F), 1.0, atol=1e-4)
    # Each particle moved 0.15 m along y (modulo the period).
    shift = (s.x[:, 1] - p.x[:, 1]) % (hi - lo)
    assert np.all(np.minimum(shift, hi - lo - shift) < 1e-3)
    assert solver.face_contacts == 0


def test_wall_and_periodic_settings_are_checked():
    with pytest.raises(ValueError, match="mode='rough' unknown"):
        SideWall(0, 0.0, mode="rough")
    with pytest.raises(ValueError, match="lo < hi"):
        PeriodicAxis(1, 0.1, 0.0)
    p = block()
    grid = GridSpec.fit((0.0, 0.0, 0.0), (0.2, 0.2, 0.2), DX)
    with pytest.raises(ValueError, match="must lie on grid nodes"):
        MPMSolver(p, [JELLY], grid, Scene(periodic=(PeriodicAxis(1, 0.001, 0.15),)))
