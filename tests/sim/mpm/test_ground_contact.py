"""Ground contact at the surface (issue 24 item 3): where impacts begin and bodies rest, friction
and restitution, for the particle contact (``particle_ground``) and the grid condition held at
``SURFACE_DEPTH`` (``boundary``, ``surface_friction``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from physgm.bench.verification import analytic as V
from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm import reference_mpm
from physgm.sim.mpm.boundary import MAX_DAMPING, SURFACE_DEPTH, GroundPlane
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.solver import MPMSolver
from physgm.sim.mpm.state import Particles
from physgm.sim.mpm.stepping import SolverConfig

G = 9.81
DX = 0.02
SP = DX / 2  # particle spacing: the lowest particles sit SP / 2 above the block's bottom face


def _block(
    bottom: float,
    ground: GroundPlane,
    frame_dt: float,
    damping: float = 0.0,
    origin_z: float = 0.0,
    E: float = 5e4,
    vx: float = 0.0,
):
    """An 8 x 8 x 5 cm elastic block (lowest particles at ``bottom``) above the plane z = 0."""
    p = Particles.lattice((-0.04, -0.04, bottom - SP / 2), (0.04, 0.04, bottom - SP / 2 + 0.05), SP)
    p.v = np.tile([vx, 0.0, 0.0], (len(p), 1))
    mat = MaterialParams("fixed_corotated", E, 0.3, 1000.0)
    grid = GridSpec.fit((-0.08, -0.08, origin_z), (0.08 + 2 * vx, 0.08, bottom + 0.08), DX)
    scene = Scene(ground=ground, damping=damping)
    return MPMSolver(p, [mat], grid, scene, SolverConfig(frame_dt=frame_dt, threads=1))


GROUNDS = {  # name -> GroundPlane(mode, friction): the particle contact and the held nodes
    "particles": lambda mode, friction: GroundPlane(0.0, friction=friction, mode=mode, contact="particles"),
    "nodes_at_surface": lambda mode, friction: GroundPlane(
        0.0, friction=friction, mode=mode, held_depth=SURFACE_DEPTH
    ),
}
CASES = [
    ("particles", "slip", 0.0),
    ("particles", "separate", 0.5),
    ("nodes_at_surface", "slip", 0.0),
    ("nodes_at_surface", "separate", 0.5),
    ("nodes_at_surface", "sticky", 0.0),
]


@pytest.mark.parametrize("contact, mode, friction", CASES)
def test_dropped_block_rests_with_its_lowest_particles_on_the_plane(contact, mode, friction):
    # Dropped 3 cm; a drag settles the bounce. The lowest particles lie half a particle spacing
    # (a quarter cell) above the block's bottom face, so at rest on the plane they are at 0.25 dx.
    solver = _block(0.03, GROUNDS[contact](mode, friction), 0.04, damping=15.0)
    for _ in range(20):
        solver.step_frame()
    z_low = float(solver.state().x[:, 2].min())
    assert abs(z_low) <= 0.25 * DX, f"lowest particle {z_low / DX:.3f} dx from the plane"
    if contact == "particles":  # the surface on the plane: the particles at 0.25 dx within 0.02 dx
        assert z_low == pytest.approx(0.25 * DX, abs=0.02 * DX)


def test_default_contact_is_on_the_particles_except_for_sticky_or_held_grounds():
    assert GroundPlane().contact == "particles" and GroundPlane(mode="slip").contact == "particles"
    assert GroundPlane(mode="sticky").contact == "nodes"
    assert GroundPlane(held_depth=SURFACE_DEPTH).contact == "nodes"
    assert GroundPlane().on_nodes().contact == "nodes"
    with pytest.raises(ValueError, match="damping"):
        GroundPlane(contact="particles", damping=MAX_DAMPING + 0.01)
    with pytest.raises(ValueError, match="rest_damping"):
        GroundPlane(rest_damping=-0.1)


def test_node_ground_at_the_plane_holds_bodies_a_cell_high():
    # The grid condition at the plane (contact="nodes", held_depth = 0; the particle contact's
    # predecessor as the default): the nodes at the plane hold the block about a cell above it.
    solver = _block(0.03, GroundPlane(0.0, friction=0.0, mode="slip", contact="nodes"), 0.04, damping=15.0)
    for _ in range(20):
        solver.step_frame()
    assert float(solver.state().x[:, 2].min()) > 0.75 * DX


def test_grid_is_aligned_to_the_ground_and_rest_height_does_not_depend_on_it():
    # A grid is lowered by a fraction of a cell to put a node plane SURFACE_DEPTH cells under the
    # ground; the result does not depend on where the given grid's nodes were.
    ground = GroundPlane(0.0, friction=0.0, mode="slip", held_depth=SURFACE_DEPTH)
    lows = []
    for origin_z in (0.0, -0.37 * DX):
        solver = _block(0.03, ground, 0.04, damping=15.0, origin_z=origin_z)
        k = (0.0 - SURFACE_DEPTH * DX - solver.grid.origin[2]) / DX
        assert k == pytest.approx(round(k), abs=1e-6)
        for _ in range(20):
            solver.step_frame()
        lows.append(float(solver.state().x[:, 2].min()))
    assert lows[0] == pytest.approx(lows[1], abs=0.02 * DX)


@pytest.mark.parametrize("contact", sorted(GROUNDS))
def test_impact_begins_when_the_bottom_face_reaches_the_plane(contact):
    # Free fall until the ground acts: the first frame whose mean velocity leaves the ballistic
    # one (by 1 % of the impact speed) dates the first contact; the bottom face (SP / 2 below the
    # lowest particles) is then within a quarter cell of the plane. Nodes at the plane: ~1 cell up.
    bottom = 0.04
    frame_dt = 0.001
    solver = _block(bottom, GROUNDS[contact]("slip", 0.0), frame_dt)
    face = bottom - SP / 2
    v_hit = math.sqrt(2 * G * face)
    t, dev = [0.0], [0.0]
    while solver.time < math.sqrt(2 * face / G) + 0.02:
        solver.step_frame()
        t.append(solver.time)
        dev.append(float(solver.state().v[:, 2].astype(np.float64).mean()) + G * solver.time)
    t, dev = np.array(t), np.array(dev)
    k = int(np.argmax(dev > 0.01 * v_hit))
    assert k > 0, "the block never touched the ground"
    t_contact = t[k - 1] + (0.01 * v_hit - dev[k - 1]) / (dev[k] - dev[k - 1]) * frame_dt
    height = face - 0.5 * G * t_contact**2  # the bottom face's height at first contact, m
    assert abs(height) <= 0.25 * DX, f"contact began with the bottom face {height / DX:.3f} dx from the plane"


@pytest.mark.parametrize("contact", sorted(GROUNDS))
def test_block_pushed_along_a_coulomb_floor_slides_the_coulomb_distance(contact):
    # A stiff block resting on the plane, thrown sideways at 0.3 m/s on a mu = 0.4 floor: it
    # stops after v^2 / (2 mu g) = 11.5 mm, at the surface. It starts where each ground holds it
    # at rest: its surface on the plane (particle contact: a start 0.05 dx lower would compress
    # the contact springs by 1 mm, 500 times their load, and throw the block up) or its lowest
    # particles at 0.2 dx (held nodes).
    bottom = 0.25 * DX if contact == "particles" else 0.2 * DX
    solver = _block(bottom, GROUNDS[contact]("separate", 0.4), 0.01, E=1e6, vx=0.3)
    x0 = solver.state().x[:, 0].mean()
    for _ in range(20):
        solver.step_frame()
    x = solver.state().x
    slide = float(x[:, 0].mean() - x0)
    assert slide == pytest.approx(0.3**2 / (2 * 0.4 * G), rel=0.1)
    assert float(np.abs(solver.state().v[:, 0]).max()) < 0.01  # it stopped
    assert abs(float(x[:, 2].min())) <= 0.25 * DX


def test_slow_slide_on_the_particle_contact_stops_near_the_coulomb_distance():
    # The same block thrown at 0.03 m/s: Coulomb stops it after 0.115 mm. Below mu f_n the
    # particle friction is viscous, capped at m |v_t| / (cfl tau), the most that never reverses a
    # particle within a sub-step (particle_ground); measured 0.148 mm (with m |v_t| / tau instead:
    # 0.205 mm, a slow creep past the stop).
    solver = _block(0.25 * DX, GROUNDS["particles"]("separate", 0.4), 0.01, E=1e6, vx=0.03)
    x0 = solver.state().x[:, 0].mean()
    for _ in range(20):
        solver.step_frame()
    slide = float(solver.state().x[:, 0].mean() - x0)
    solver.close()
    coulomb = 0.03**2 / (2 * 0.4 * G)
    assert 0.9 * coulomb < slide < 1.5 * coulomb, (slide, coulomb)


def test_block_pushed_along_a_sticky_floor_does_not_slide_or_lift():
    # The block of the Coulomb test on a sticky ground at the surface: its lowest particles
    # stop within 0.1 dx (2 mm; on the mu = 0.4 floor they slide 11.5 mm) and stay down.
    ground = GroundPlane(0.0, mode="sticky", held_depth=SURFACE_DEPTH)
    solver = _block(0.2 * DX, ground, 0.01, E=1e6, vx=0.3)
    x0 = solver.state().x
    bottom = x0[:, 2] < x0[:, 2].min() + 0.1 * SP  # the lowest layer of particles
    for _ in range(10):
        solver.step_frame()
    x = solver.state().x
    assert float(np.abs(x[bottom, 0] - x0[bottom, 0]).max()) < 0.1 * DX
    assert float(np.abs(x[bottom, 2] - x0[bottom, 2]).max()) < 0.1 * DX


def test_surface_friction_matches_the_numpy_twin(monkeypatch):
    # A block sliding at the surface of a Coulomb ground: three sub-steps against the twin,
    # which also shows that the surface layer's friction acts (the twin without it differs).
    p = Particles.lattice((-0.02, -0.02, 0.1 * DX), (0.02, 0.02, 0.1 * DX + 0.03), SP)
    p.v = np.tile([0.5, 0.1, -2.0], (len(p), 1))  # an impact: the held nodes stick and leave grip
    mat = MaterialParams("fixed_corotated", 1e5, 0.3, 1000.0)
    scene = Scene(ground=GroundPlane(0.0, friction=0.4, held_depth=SURFACE_DEPTH))
    grid = GridSpec.fit((-0.05, -0.05, 0.0), (0.05, 0.05, 0.05), DX)
    solver = MPMSolver(p, [mat], grid, scene, SolverConfig(flip=0.0, threads=1))
    s0 = solver.state()
    state = {
        "x": s0.x,
        "v": s0.v,
        "C": s0.C,
        "F": s0.F,
        "plastic": s0.plastic,
        "mass": 1000.0 * np.broadcast_to(p.volume, len(p)),
        "vol0": np.broadcast_to(p.volume, len(p)),
    }
    state = {k: np.asarray(val, dtype=np.float64) for k, val in state.items()}
    state["material"] = p.material
    bound = SolverConfig().boundary_cells
    for _ in range(3):
        out = reference_mpm.substep(state, [mat], solver.grid, scene, 2e-4, solver.time, 0.0, bound)
        solver.substep(2e-4)
        state.update({k: out[k] for k in ("x", "v", "C", "F", "plastic")})
    s1 = solver.state()
    solver.close()
    np.testing.assert_allclose(s1.v, state["v"], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(s1.x, state["x"], rtol=1e-6, atol=1e-6)
    low = s1.x[:, 2] < s1.x[:, 2].min() + 0.5 * SP  # the lowest layer of particles
    held = reference_mpm.substep(state, [mat], solver.grid, scene, 2e-4, solver.time, 0.0, bound)
    monkeypatch.setattr(reference_mpm, "_surface_friction", lambda *args: None)
    free = reference_mpm.substep(state, [mat], solver.grid, scene, 2e-4, solver.time, 0.0, bound)
    assert held["v"][low, 0].mean() < free["v"][low, 0].mean() - 0.005  # m/s, in one sub-step


@pytest.mark.parametrize(
    "contact, held_depth, damping",
    [
        ("particles", 0.0, None),
        ("particles", 0.0, 0.0),
        ("particles", 0.0, MAX_DAMPING),
        ("nodes", SURFACE_DEPTH, 0.0),
    ],
)
def test_elastic_ball_keeps_its_restitution(contact, held_depth, damping):
    # The particle contact's dashpot, even at its largest zeta, takes little of the bounce: it acts
    # on the bottom layer only (measured 0.938 elastic, 0.914 at the default zeta 0.2, 0.908 at 0.25).
    result = V.ball_restitution(fast=True, E=1e5, held_depth=held_depth, contact=contact, damping=damping)
    assert result["restitution"] >= 0.9, result


def test_contact_dashpot_takes_energy_at_impact():
    # The test block dropped 3 cm with no drag: the dashpot (default zeta) lowers its first
    # rebound (centre of mass 37.4 against 42.3 mm elastic, measured) and leaves it ringing less.
    peaks = []
    for zeta in (0.0, GroundPlane().damping):
        ground = GroundPlane(0.0, friction=0.0, mode="slip", contact="particles", damping=zeta)
        solver = _block(0.03, ground, 0.005)
        com = []
        for _ in range(50):
            solver.step_frame()
            com.append(float(solver.state().x[:, 2].mean()))
        solver.close()
        first = int(np.argmin(com[:30]))
        peaks.append(max(com[first:]))
    assert GroundPlane().damping > 0 and peaks[1] < peaks[0] - 0.002, peaks


def test_resting_dashpot_stops_a_tilted_block_rocking_sooner():
    # A stiff 8 x 8 x 5 cm block tilted 15 degrees lands on one edge and rocks on its springs; the
    # resting dashpot (particle_ground) damps the slow approaches of that rocking on the grid, so
    # every particle comes to rest sooner: measured at frame 21 against 32 without it (20 ms frames,
    # largest per-frame motion under 0.01 mm).
    def quiet_frame(rest_damping: float) -> int:
        p = Particles.lattice((-0.04, -0.04, -0.025), (0.04, 0.04, 0.025), SP)
        a = np.radians(15.0)
        x = p.x @ np.array([[1, 0, 0], [0, np.cos(a), np.sin(a)], [0, -np.sin(a), np.cos(a)]])
        x[:, 2] += 0.02 + SP / 2 - x[:, 2].min()  # lowest particle surface 2 cm up
        mat = MaterialParams("fixed_corotated", 1e6, 0.3, 1000.0)
        grid = GridSpec.fit((-0.1, -0.1, 0.0), (0.1, 0.1, 0.12), DX)
        ground = GroundPlane(0.0, friction=0.3, contact="particles", rest_damping=rest_damping)
        solver = MPMSolver(
            Particles(x=x, volume=p.volume, material=0), [mat], grid, Scene(ground=ground),
            SolverConfig(frame_dt=0.02, threads=1),
        )  # fmt: skip
        previous, moved = solver.state().x, []
        for _ in range(40):
            solver.step_frame()
            now = solver.state().x
            moved.append(float(np.linalg.norm(now - previous, axis=1).max()))
            previous = now
        solver.close()
        return int(np.argmax(np.array(moved) < 1e-5)) + 1

    default = GroundPlane().rest_damping
    assert default > 0 and quiet_frame(default) + 8 <= quiet_frame(0.0)
