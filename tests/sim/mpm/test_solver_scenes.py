"""Scene registry and drivers: drop, stretch, push, two objects of different materials."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import brentq

from physgm.physics.materials import get_material
from physgm.sim.mpm import GridSpec, MPMSolver, Particles, SolverConfig
from physgm.sim.mpm.particle_ground import contact_plane
from physgm.sim.planner import PlannerConfig, stretch_splits
from physgm.sim.sampling import ParticleSample, split_along
from physgm.sim.scenes import SCENES, build_scene

SP = 0.0125  # particle spacing, m (dx = 2 SP)


def cube(size=0.1, material=0) -> Particles:
    return Particles.lattice((0.0, 0.0, 0.0), (size, size, size), SP, material=material)


def make_solver(p: Particles, setup, materials, frame_dt=0.02, pad=0.05, dx=2 * SP):
    p.x = setup.x
    p.v = setup.v
    grid = GridSpec.fit(setup.reach_lo - pad, setup.reach_hi + pad, dx)
    return MPMSolver(p, materials, grid, setup.scene, SolverConfig(frame_dt=frame_dt))


def test_registry_and_errors():
    assert set(SCENES) == {"drop", "stretch", "push", "two_objects"}
    with pytest.raises(ValueError, match="unknown scene 'spin'.*drop"):
        build_scene("spin", np.zeros((4, 3)))
    with pytest.raises(ValueError, match="has no settings \\['hieght'\\]"):
        build_scene("drop", np.zeros((4, 3)), hieght=1.0)
    with pytest.raises(ValueError, match="finite"):
        build_scene("drop", np.full((4, 3), np.nan))


def test_heights_and_gaps_are_the_materials_not_the_particle_centres():
    """With ``surface`` (half the lattice spacing) a scene places the material's lowest surface:
    a drop's height and a push's lift are measured from it, and the two objects' gap is between
    their surfaces; the particle contact then starts uncompressed, as the rigid path takes the body."""
    p, half = cube(), 0.5 * SP
    drop = build_scene("drop", p.x, surface=half, height=0.05)
    assert drop.x[:, 2].min() - half == pytest.approx(0.05)
    push = build_scene("push", p.x, surface=half)
    assert push.x[:, 2].min() - half == pytest.approx(0.0)
    assert contact_plane(push.scene.ground, push.x, p.volume) == pytest.approx(0.0, abs=1e-9)
    pair = Particles.cat([cube(0.1, material=0), cube(0.075, material=1)])
    two = build_scene("two_objects", pair.x, pair.material, surface=half, gap=0.08)
    upper, lower = two.x[pair.material == 1], two.x[pair.material == 0]
    assert lower[:, 2].min() - half == pytest.approx(0.0)
    assert (upper[:, 2].min() - half) - (lower[:, 2].max() + half) == pytest.approx(0.08)
    with pytest.raises(ValueError, match="surface"):
        build_scene("drop", p.x, surface=-0.01)


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


def test_stretch_grips_move_their_particles_apart_until_the_ratio():
    """The grips hold nodes only (their particles follow the nodes), so the grid must resolve
    them: 10 cells across, a grip a cell deep. They stop once the extent grew by (ratio - 1) x."""
    p = Particles.lattice((0.0, 0.0, 0.0), (0.1, 0.1, 0.1), 0.005)
    setup = build_scene("stretch", p.x, speed=0.5, ratio=1.5, duration=0.2)
    assert setup.driver_work and len(setup.scene.boxes) == 2
    solver = make_solver(p, setup, [get_material("jelly").params(E=5e4)], frame_dt=0.01, dx=0.01)
    left, right = p.x[:, 0] < np.quantile(p.x[:, 0], 0.1), p.x[:, 0] > np.quantile(p.x[:, 0], 0.9)
    for _ in range(12):
        solver.step_frame()
    x = solver.state().x
    length0 = p.x[right, 0].mean() - p.x[left, 0].mean()
    grown = x[right, 0].mean() - x[left, 0].mean()
    # The extent 0.095 m grows by half of itself at 1 m/s in all, by 0.0475 s; held after that.
    assert grown - length0 == pytest.approx(0.0475, rel=0.05)
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


def test_stretch_leaves_a_prism_in_uniform_uniaxial_tension():
    """Slip grips pull a jelly prism to twice its length, its particles split along the axis as
    the planner asks: the middle narrows as fixed-corotated uniaxial tension says (lateral stress
    0), keeps the volume ratio that goes with it, and no layer of particles tears away."""
    dx, size = 0.01, 0.08
    base = Particles.lattice((-size / 2,) * 3, (size / 2,) * 3, dx / 2)
    first = build_scene("stretch", base.x, axis=1, speed=0.5, ratio=2.0, duration=0.25)
    n = stretch_splits(first.stretch[1], dx / 2, dx, PlannerConfig())
    assert first.stretch[0] == 1 and n == 2  # a prism's peak stretch is its mean: 2.2x over 0.8 of it
    rest = torch.from_numpy(base.x).float()
    volume = torch.full((len(rest),), (dx / 2) ** 3)
    lattice = ParticleSample(rest, volume, torch.zeros(len(rest), dtype=bool), dx / 2)
    sample = split_along(lattice, 1, n)
    p = Particles(x=sample.x.double().numpy(), volume=sample.volume.double().numpy(), material=0)
    setup = build_scene("stretch", p.x, axis=1, speed=0.5, ratio=2.0, duration=0.25)
    E, nu = 5e4, 0.45
    solver = make_solver(p, setup, [get_material("jelly").params(E=E, nu=nu)], frame_dt=0.01, pad=0.02, dx=dx)
    x0 = setup.x
    mid = np.abs(x0[:, 1]) < 0.2 * size  # the middle 40 %
    layer = np.round((x0[:, 1] - x0[:, 1].min()) / (dx / 4)).astype(int)
    lateral, axial, J, worst = [], [], [], []
    for frame in range(25):
        solver.step_frame()
        if frame >= 15:  # grips held from 0.08 s; the last 0.1 s averages the ringing out
            s = solver.state()
            axial.append(s.x[mid, 1].std() / x0[mid, 1].std())
            lateral.append(s.x[mid][:, [0, 2]].std(0).mean() / x0[mid][:, [0, 2]].std(0).mean())
            J.append(np.median(np.linalg.det(s.F[mid])))
            y = np.array([np.median(s.x[layer == i, 1]) for i in range(layer.max() + 1)])
            gaps = np.diff(y)
            worst.append(gaps.max() / np.median(gaps))
    stretch_mid, t, j = np.mean(axial), np.mean(lateral), np.mean(J)
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))

    def lateral_stress(t_: float) -> float:  # principal Kirchhoff stress across the axis, J = s t^2
        J_ = stretch_mid * t_**2
        return 2 * mu * (t_ - 1) * t_ + lam * (J_ - 1) * J_

    t_exact = brentq(lateral_stress, 0.3, 1.0)  # no stress across: uniaxial tension
    assert 1.8 < stretch_mid < 2.4
    assert t == pytest.approx(t_exact, rel=0.03)
    assert j == pytest.approx(stretch_mid * t_exact**2, rel=0.03)
    assert max(worst) < 2.0  # a torn layer opens a gap several times the others
    solver.close()


def test_stretch_reads_a_rounder_body_as_stretched_more_next_to_its_grips():
    """Grips hold a share of the particles; the peak stretch of a prism is its mean (the part
    between the grips takes the whole extension), a ball's is larger (its thin ends take more)."""
    sp = 0.005
    prism = Particles.lattice((-0.05,) * 3, (0.05,) * 3, sp).x
    ball = prism[np.linalg.norm(prism, axis=1) < 0.05]
    for x in (prism, ball):
        setup = build_scene("stretch", x, axis=2, ratio=2.0, grip_fraction=0.1)
        inner = np.quantile(x[:, 2], [0.1, 0.9])
        grips = [((setup.x >= b.lo) & (setup.x <= b.hi)).all(1).mean() for b in setup.scene.boxes]
        assert grips == pytest.approx([0.1, 0.1], abs=0.03)  # a share of the particles each
        mean = 1.0 + (x[:, 2].max() - x[:, 2].min()) / (inner[1] - inner[0])
        if x is prism:
            assert setup.stretch[1] == pytest.approx(mean, rel=0.06)
        else:
            assert setup.stretch[1] > 1.2 * mean
    with pytest.raises(ValueError, match="slip or clamp"):
        build_scene("stretch", prism, grip="glue")
