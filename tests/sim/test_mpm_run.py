"""``mpm_run``'s pieces on their own: the grid that follows a body (``followed_grid``) and the
solver resumed under it (``_resumed``). ``simulate`` end to end: ``test_planner_run.py``."""

from __future__ import annotations

import numpy as np
import pytest

from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm.boundary import GroundPlane
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.solver import MPMSolver
from physgm.sim.mpm.state import Particles
from physgm.sim.mpm.stepping import SolverConfig
from physgm.sim.mpm_run import GRID_ROOM, _moved_grid, _resumed, followed_grid

DX = 0.02
MARGIN = 3  # SolverConfig.boundary_cells
FRAME = 0.04  # s
G = 9.81  # m/s^2


def _block(centre_x: float, half: float = 0.05) -> np.ndarray:  # [P, 3] a block's particles, m
    g = np.linspace(-half, half, 6)
    pts = np.stack(np.meshgrid(g, g, g + half, indexing="ij"), -1).reshape(-1, 3)
    return pts + np.array([centre_x, 0.0, 0.0])


def test_the_grid_stays_while_the_body_is_clear_of_its_faces():
    grid = GridSpec.fit((-0.3, -0.3, 0.0), (0.3, 0.3, 0.2), DX, MARGIN)
    x = _block(0.0)
    assert followed_grid(grid, x, np.zeros_like(x), FRAME, MARGIN) is None
    # 1 m/s along x: a frame's travel still ends inside the free interior.
    assert followed_grid(grid, x, np.tile([1.0, 0.0, 0.0], (len(x), 1)), FRAME, MARGIN) is None


def test_the_grid_moves_by_whole_cells_to_centre_a_body_near_a_face():
    grid = GridSpec.fit((-0.3, -0.3, 0.0), (0.3, 0.3, 0.2), DX, MARGIN)
    x = _block(0.22)  # 3 cm of the free interior left on its +x side
    v = np.tile([1.0, 0.0, 0.0], (len(x), 1))
    moved = followed_grid(grid, x, v, FRAME, MARGIN)
    assert moved is not None and moved.res == grid.res and moved.dx == grid.dx
    shift = (np.asarray(moved.origin) - np.asarray(grid.origin)) / DX
    assert np.allclose(shift, np.round(shift), atol=1e-6) and shift[0] > 0 and shift[1] == 0 == shift[2]
    lo, hi = moved.interior(MARGIN + 1)
    assert abs(0.5 * (lo[0] + hi[0]) - 0.22) <= 0.5 * DX + 1e-9  # centred to within half a cell
    assert followed_grid(moved, x, v, FRAME, MARGIN) is None


def test_the_grid_widens_where_the_body_and_its_reach_no_longer_fit():
    grid = GridSpec.fit((-0.15, -0.1, 0.0), (0.15, 0.1, 0.2), DX, MARGIN)
    x = _block(0.0, half=0.09)
    v = np.tile([0.0, 2.0, 0.0], (len(x), 1))  # a frame's reach 2 x 0.04 = 0.08 m along y
    moved = followed_grid(grid, x, v, FRAME, MARGIN)
    assert moved is not None and moved.res[0] == grid.res[0] and moved.res[2] == grid.res[2]
    added = moved.res[1] - grid.res[1]
    assert added > 0 and added % 2 == 0
    lo, hi = moved.interior(MARGIN + 1)
    assert lo[1] <= -0.09 - 0.08 and hi[1] >= 0.09 + 0.08
    assert followed_grid(moved, x, v, FRAME, MARGIN) is None


def test_a_grid_past_the_solvers_node_cap_is_not_moved_to():
    grid = GridSpec.fit((-0.1, -0.1, 0.0), (0.1, 0.1, 0.2), DX, MARGIN)
    x = _block(0.0, half=0.09)
    v = np.tile([0.0, 0.5, 0.0], (len(x), 1))  # 2 cells short along y: the room adds 6
    wider = followed_grid(grid, x, v, FRAME, MARGIN)
    roomy = followed_grid(grid, x, v, FRAME, MARGIN, room=GRID_ROOM)
    assert wider is not None and grid.num_nodes < wider.num_nodes < roomy.num_nodes
    assert _moved_grid(grid, x, v, FRAME, SolverConfig(max_grid_nodes=roomy.num_nodes)) == roomy
    # Without the room to spread into when that alone passes the cap.
    assert _moved_grid(grid, x, v, FRAME, SolverConfig(max_grid_nodes=roomy.num_nodes - 1)) == wider
    tight = SolverConfig(max_grid_nodes=wider.num_nodes - 1)
    assert _moved_grid(grid, x, v, FRAME, tight) is None  # the walls stay, as without following


def test_a_spreading_body_moves_a_grid_with_room_a_few_times():
    """A sheet spreading along x at 1 m/s (sand after its landing), frame after frame: with no room
    the grid widens at every frame, with a quarter of its width at a time every few frames, and
    each widened grid holds the sheet and its reach."""
    grid0 = GridSpec.fit((-0.15, -0.15, 0.0), (0.15, 0.15, 0.1), DX, MARGIN)
    moves = {}
    for room in (0.0, GRID_ROOM):
        grid, count = grid0, 0
        for frame in range(30):
            half = 0.1 + 1.0 * FRAME * frame
            x = np.stack([np.linspace(-half, half, 50), np.zeros(50), np.full(50, 0.01)], -1)
            v = np.stack([np.linspace(-1.0, 1.0, 50), np.zeros(50), np.zeros(50)], -1)
            moved = followed_grid(grid, x, v, FRAME, MARGIN, room)
            if moved is not None:
                if room > 0 and moved.res[0] > grid.res[0]:
                    assert moved.res[0] - grid.res[0] >= room * grid.res[0]
                grid, count = moved, count + 1
            lo, hi = grid.interior(MARGIN + 1)
            assert lo[0] <= -half - FRAME and hi[0] >= half + FRAME
        moves[room] = count
    assert moves[0.0] >= 25 and moves[GRID_ROOM] <= 8, moves


def _rising(z_bottom: float, vz: float) -> tuple[np.ndarray, np.ndarray]:  # a block at z_bottom, moving at vz
    x = _block(0.0, half=0.04) + np.array([0.0, 0.0, z_bottom])
    return x, np.tile([0.0, 0.0, vz], (len(x), 1))


def test_the_grid_rises_with_a_rebound_and_comes_back_to_its_floor():
    """A grid cut short above the ground (a tall drop's, ``planner.domain``): a block rebounding at
    2 m/s near its top moves it up by whole cells on the floor's lattice; falling back, the block
    brings it down again, never below the floor; at the floor a block on the ground leaves it."""
    grid = GridSpec.fit((-0.2, -0.2, 0.0), (0.2, 0.2, 0.4), DX, MARGIN)
    floor = grid.origin[2]
    x, v = _rising(0.0, 0.0)
    assert followed_grid(grid, x, v, FRAME, MARGIN, floor=floor, gravity=G) is None
    x, v = _rising(0.27, 2.0)  # top 0.35 m, a frame's reach 0.08 + 0.008 m: past the 0.4 m interior
    up = followed_grid(grid, x, v, FRAME, MARGIN, floor=floor, gravity=G)
    assert up is not None and up.res == grid.res and up.origin[:2] == grid.origin[:2]
    cells = (up.origin[2] - floor) / DX
    assert cells > 0 and abs(cells - round(cells)) < 1e-6
    lo, hi = up.interior(MARGIN + 1)
    assert lo[2] <= 0.27 - 0.088 and hi[2] >= 0.35 + 0.088
    # Without a floor z stays as planned, as before: x and y hold the block.
    assert followed_grid(grid, x, v, FRAME, MARGIN) is None
    x, v = _rising(0.02, -3.0)  # back near the ground, falling
    down = followed_grid(up, x, v, FRAME, MARGIN, floor=floor, gravity=G)
    assert down is not None and down.origin[2] == pytest.approx(floor, abs=1e-12)
    assert followed_grid(down, x, v, FRAME, MARGIN, floor=floor, gravity=G) is None


def test_a_moved_grid_holds_particles_a_hard_landing_drove_under_its_floor():
    """Particles 3 cm under the ground (a landing at many times the wave speed, through the contact
    springs): a move for the sideways spread goes below the floor as far as they need, since a
    solver is built only around particles inside its interior."""
    grid = GridSpec.fit((-0.2, -0.2, 0.0), (0.2, 0.2, 0.4), DX, MARGIN)
    floor = grid.origin[2]
    x, _ = _rising(-0.03, 0.0)
    v = np.tile([2.0, 0.0, 0.0], (len(x), 1))
    moved = followed_grid(grid, x, v, FRAME, MARGIN, floor=floor, gravity=G)
    lo, hi = moved.interior(MARGIN + 1)
    assert moved.origin[2] < floor and lo[2] <= -0.03 and hi[2] >= 0.05
    cells = (moved.origin[2] - floor) / DX
    assert abs(cells - round(cells)) < 1e-6


def test_a_resumed_solver_keeps_the_contact_plane_of_the_first():
    """A soft block (E = 1e4 Pa) resting on the contact springs, its surface on the plane. A solver
    started afresh from its state would lower the plane by the springs' compression (0.13 of a
    spacing here, measured) and the block would sink by it at every rebuild; the solver that
    continues a run (``_resumed``, as when the grid moves) keeps the first plane."""
    sp = DX / 2
    p = Particles.lattice((-0.04, -0.04, 0.0), (0.04, 0.04, 0.08), sp)
    soft = MaterialParams("fixed_corotated", 1e4, 0.3, 1000.0)
    grid = GridSpec.fit((-0.08, -0.08, 0.0), (0.08, 0.08, 0.1), DX)
    scene = Scene(ground=GroundPlane(0.0, friction=0.3, contact="particles"))
    cfg = SolverConfig(threads=1)
    first = MPMSolver(p, [soft], grid, scene, cfg)
    for _ in range(20):  # it settles on the springs
        first.step_frame()
    state = first.state()
    resume, continued = _resumed(first, state, p.volume, scene)
    plane = first.launches.contact_height
    assert continued.ground.contact_height == plane == pytest.approx(0.0, abs=1e-6)
    first.close()
    afresh = MPMSolver(resume, [soft], grid, scene, cfg)
    assert afresh.launches.contact_height < -0.1 * sp  # what it avoids
    afresh.close()
    solver = MPMSolver(resume, [soft], grid, continued, cfg)
    assert solver.launches.contact_height == plane
    low0 = float(state.x[:, 2].min())
    for _ in range(5):
        solver.step_frame()
    low = float(solver.state().x[:, 2].min())
    solver.close()
    assert abs(low - low0) < 0.01 * sp, (low - low0) / sp  # measured 0.0004 of a spacing (afresh: 0.13)


def test_a_contact_height_above_the_ground_is_refused():
    with pytest.raises(ValueError, match="contact_height"):
        GroundPlane(0.0, contact_height=0.01)
