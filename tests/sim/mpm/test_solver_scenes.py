"""Scene registry and drivers: drop, stretch, push, two objects of different materials."""

from __future__ import annotations

import numpy as np
import pytest

from physgm.physics.materials import get_material
from physgm.sim.mpm import GridSpec, MPMSolver, Particles, SolverConfig
from physgm.sim.scenes import SCENES, build_scene

SP = 0.0125  # particle spacing, m (dx = 2 SP)


def cube(size=0.1, material=0) -> Particles:
    return Particles.lattice((0.0, 0.0, 0.0), (size, size, size), SP, material=material)


def make_solver(p: Particles, setup, materials, frame_dt=0.02, pad=0.05):
    p.x = setup.x
    p.v = setup.v
    grid = GridSpec.fit(setup.reach_lo - pad, setup.reach_hi + pad, 2 * SP)
    return MPMSolver(p, materials, grid, setup.scene, SolverConfig(frame_dt=frame_dt))


def test_registry_and_errors():
    assert set(SCENES) == {"drop", "stretch", "push", "two_objects"}
    with pytest.raises(ValueError, match="unknown scene 'spin'.*drop"):
        build_scene("spin", np.zeros((4, 3)))
    with pytest.raises(ValueError, match="has no settings \\['hieght'\\]"):
        build_scene("drop", np.zeros((4, 3)), hieght=1.0)
    with pytest.raises(ValueError, match="finite"):
        build_scene("drop", np.full((4, 3), np.nan))


def test_drop_lands_on_the_ground():
    p = cube()
    setup = build_scene("drop", p.x, height=0.05, duration=0.3)
    assert setup.x[:, 2].min() == pytest.approx(0.05)
    solver = make_solver(p, setup, [get_material("rubber").params(E=3e5)])
    lowest = []
    for _ in range(15):
        solver.step_frame()
        lowest.append(solver.state().x[:, 2].min())
    lowest = np.array(lowest)
    assert lowest.min() > -2 * SP  # no penetration beyond a cell
    landed = int(np.argmax(lowest < 0.02))  # it did fall onto the ground (from 0.05 m) ...
    assert lowest[landed] < 0.02
    assert lowest[landed:].max() > lowest[landed] + 0.005  # ... and the rubber bounced back up
    assert solver.escaped == 0


def test_stretch_doubles_the_length():
    p = cube()
    setup = build_scene("stretch", p.x, speed=0.5, ratio=2.0, duration=0.2)
    assert setup.driver_work and len(setup.scene.boxes) == 2
    solver = make_solver(p, setup, [get_material("jelly").params(E=5e4)], frame_dt=0.01)
    left, right = p.x[:, 0] < 0.01, p.x[:, 0] > 0.09
    for _ in range(12):
        solver.step_frame()
    x = solver.state().x
    length0 = p.x[right, 0].mean() - p.x[left, 0].mean()
    grown = x[right, 0].mean() - x[left, 0].mean()
    # Grips stop once the particle extent doubled (0.0875 m of growth at 1 m/s total).
    assert grown - length0 == pytest.approx(0.0875, rel=0.05)
    assert solver.driver_work > 0 and np.isfinite(x).all()


def test_push_stops_at_the_wall():
    p = cube()
    setup = build_scene("push", p.x, speed=2.0, wall_gap=0.05, duration=0.3)
    wall_x = setup.scene.boxes[0].lo[0]
    solver = make_solver(p, setup, [get_material("rubber").params(E=3e5)], pad=0.1)
    front = []
    for _ in range(8):
        solver.step_frame()
        front.append(solver.state().x[:, 0].max())
    assert max(front) < wall_x + 2 * SP  # never through the wall
    assert max(front) > wall_x - 4 * SP  # it reached the wall ...
    assert front[-1] < max(front) - 0.05  # ... and bounced back


def test_two_objects_of_different_materials():
    top, bottom = cube(0.075, material=1), cube(0.1, material=0)
    p = Particles.cat([bottom, top])
    setup = build_scene("two_objects", p.x, p.material, gap=0.08, velocity=[0.0, 0.0, -1.0], duration=0.3)
    mats = [get_material("wood").params(E=5e6), get_material("jelly").params(E=5e4)]
    solver = make_solver(p, setup, mats)
    gap = []
    for _ in range(10):
        solver.step_frame()
        x = solver.state().x
        upper, lower = x[p.material == 1], x[p.material == 0]
        gap.append(upper[:, 2].min() - lower[:, 2].max())
        assert abs(lower[:, 2].min()) < 2 * SP  # the stiff block stays on the ground
    assert min(gap) > -2 * SP  # the jelly lands on the wood, not through it ...
    # ... after falling the 0.08 m gap: single-grid MPM contact acts at ~1.5 cells between particle centres
    assert min(gap) < 3 * SP
