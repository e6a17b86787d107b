"""One MPM sub-step against the numpy twin; bounds, guard, threads, sorting, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm import (
    GridSpec,
    GroundPlane,
    MPMSolver,
    Particles,
    Scene,
    SimulationDiverged,
    SolverConfig,
    VelocityBox,
    reference_mpm,
    run_solver,
)
from physgm.sim.mpm.grid_layout import from_dense, to_dense


def random_block(n: int, seed: int, lo=0.1, hi=0.2, material=None) -> Particles:
    rng = np.random.default_rng(seed)
    x = rng.uniform(lo, hi, (n, 3))
    p = Particles(x=x, volume=1e-6, material=0 if material is None else material)
    p.v = rng.normal(0.0, 0.5, (n, 3))
    F = np.eye(3) + 0.05 * rng.normal(size=(n, 3, 3))
    p.F = F
    return p


MATS = [
    MaterialParams("fixed_corotated", 1e5, 0.3, 1000.0),
    MaterialParams("drucker_prager", 2e5, 0.3, 1500.0, friction_angle=30.0, cohesion=100.0),
]


@pytest.mark.parametrize(
    "flip, threads, grip",
    [(0.0, 1, "clamp"), (0.0, 2, "clamp"), (0.95, 1, "clamp"), (0.95, 2, "clamp"), (0.95, 2, "slip")],
)
def test_substeps_match_numpy_twin(flip, threads, grip):
    """Three sub-steps: the first scatters with p2g, the later ones use g2p's fused scatter. A slip
    grip prescribes only the pulling component and leaves its particles to the grid."""
    rng = np.random.default_rng(3)
    p = random_block(60, seed=1, material=rng.integers(0, 2, 60))
    grid = GridSpec((0.0, 0.0, 0.0), 0.025, (14, 12, 13))  # not cubic on purpose
    slip = dict(axes=(False, True, False), carry=False) if grip == "slip" else {}
    box = VelocityBox((0.09, 0.0, 0.0), (0.13, 0.3, 0.3), (0.0, 0.3, 0.0), **slip)
    # The grid condition at the plane (random particles start under it, where the particle
    # contact's springs would push from a lowered plane; its twin: test_particle_ground.py).
    scene = Scene(ground=GroundPlane(height=0.11, friction=0.4, contact="nodes"), boxes=(box,))
    solver = MPMSolver(p, MATS, grid, scene, SolverConfig(flip=flip, threads=threads))
    s0 = solver.state()
    ref = dict(
        x=s0.x,
        v=s0.v,
        C=s0.C,
        F=s0.F,
        plastic=s0.plastic,
        mass=p.volume * np.array([1000.0, 1500.0])[p.material],
        vol0=p.volume,
        material=p.material,
    )
    ref = {k: np.asarray(val, dtype=np.float64) if k != "material" else val for k, val in ref.items()}
    for step, dt in enumerate([2e-4, 1.5e-4, 2e-4]):  # dt changes: the scatter must not depend on it
        out = reference_mpm.substep(
            ref, MATS, solver.grid, scene, dt, solver.time, flip, SolverConfig().boundary_cells
        )
        solver.substep(dt)
        s1 = solver.state()
        loose = 1 + 2 * step  # float32 against float64 drifts apart step by step
        np.testing.assert_allclose(s1.v, out["v"], rtol=1e-4 * loose, atol=1e-5 * loose)
        np.testing.assert_allclose(s1.x, out["x"], rtol=1e-6, atol=1e-7 * loose)
        np.testing.assert_allclose(s1.C, out["C"], rtol=1e-4 * loose, atol=1e-3 * loose)
        np.testing.assert_allclose(s1.F, out["F"], rtol=1e-5 * loose, atol=1e-5 * loose)
        gv = to_dense(solver.grid_v.numpy(), solver.grid.res)[..., :3]
        np.testing.assert_allclose(gv, out["grid_v"], rtol=1e-4 * loose, atol=1e-5 * loose)
        ref.update({k: out[k] for k in ("x", "v", "C", "F", "plastic")})
    if grip == "slip":  # the box held the nodes' pull and left their sideways motion free
        g = to_dense(solver.grid_v.numpy(), solver.grid.res)
        # Nodes at x = 0.1, 0.125 m (in the box), above the ground, clear of the separating walls.
        inside = g[4:6, 3:9, 6:10]
        held = inside[inside[..., 3] > 0]
        assert len(held) > 0 and (held[:, 1] == np.float32(0.3)).all()  # exactly the pull
        assert np.abs(held[:, [0, 2]]).max() > 1e-3
    solver.close()


@pytest.mark.parametrize("threads", [1, 2])
def test_block_skipping_grid_update_matches_twin_across_blocks(threads):
    """Particles thrown across several 4^3-node blocks: grid_update only updates the blocks a
    stencil reached, and nodes of blocks left behind must never be read (the twin updates all)."""
    rng = np.random.default_rng(7)
    p = Particles(x=rng.uniform(0.1, 0.14, (40, 3)), volume=1e-6, material=0)
    p.v = np.tile([6.0, -4.0, 5.0], (40, 1)) + rng.normal(0.0, 0.3, (40, 3))
    grid = GridSpec((0.0, 0.0, 0.0), 0.01, (30, 26, 29))  # blocks cut at nodes 4, 8, ...; ragged last block
    soft = [MaterialParams("fixed_corotated", 1e3, 0.3, 1000.0)]  # CFL step 4e-4 s at 9 m/s
    scene = Scene(gravity=(0.0, 0.0, -9.81))
    solver = MPMSolver(p, soft, grid, scene, SolverConfig(flip=0.0, threads=threads))
    s0 = solver.state()
    ref = {
        "x": s0.x,
        "v": s0.v,
        "C": s0.C,
        "F": s0.F,
        "plastic": s0.plastic,
        "mass": np.full(40, 1e-3),
        "vol0": np.full(40, 1e-6),
    }
    ref = {k: np.asarray(val, dtype=np.float64) for k, val in ref.items()}
    ref["material"] = p.material
    x_start = ref["x"].mean(0)
    for _ in range(30):
        out = reference_mpm.substep(ref, soft, solver.grid, solver.scene, 4e-4, solver.time, 0.0, 3)
        solver.substep(4e-4)
        ref.update({k: out[k] for k in ("x", "v", "C", "F", "plastic")})
    s1 = solver.state()
    assert np.all(np.abs(ref["x"].mean(0) - x_start) > 0.04)  # moved more than a block (4 cm) per axis
    np.testing.assert_allclose(s1.x, ref["x"], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(s1.v, ref["v"], rtol=1e-3, atol=1e-3)
    solver.close()


def test_a_thread_per_block_updates_the_grid_as_a_thread_per_slab_does():
    """grid_update launched as CUDA runs it (a thread per block, ``slabs`` 0) leaves the same node
    velocities as the CPU's thread per slab of blocks across x, on particles spread over several
    blocks of a ragged grid, with the ground."""
    rng = np.random.default_rng(11)
    p = Particles(x=rng.uniform(0.06, 0.2, (300, 3)), volume=1e-6, material=0)
    p.v = rng.normal(0.0, 0.5, (300, 3))
    grid = GridSpec((0.0, 0.0, 0.0), 0.01, (30, 26, 29))
    scene = Scene(ground=GroundPlane(height=0.07, friction=0.4, contact="nodes"))
    solver = MPMSolver(p, MATS[:1], grid, scene, SolverConfig(threads=1))
    for _ in range(3):
        solver.substep(1e-4)
    launches = solver.launches
    for launch in launches.p2g:  # the accumulators of the next sub-step, from the current state
        launch.launch()
    acc = [a.numpy().copy() for a in solver.arrays.acc]
    (update,) = launches.grid_update
    update.launch()
    slabs = solver.grid_v.numpy().copy()
    for a, saved in zip(solver.arrays.acc, acc, strict=True):
        a.assign(saved)
    solver.grid_v.zero_()
    update.set_param_by_name("slabs", 0)
    update.set_dim(solver.arrays.touched.shape)
    update.launch()
    per_block = solver.grid_v.numpy()
    assert (per_block[..., 3] > 0).sum() > 1000  # nodes with mass in many blocks
    np.testing.assert_array_equal(per_block, slabs)
    solver.close()


def test_fused_scatter_equals_a_fresh_p2g():
    """After g2p, the accumulators hold exactly what a standalone p2g of the new state gives."""
    p = random_block(400, seed=5)
    grid = GridSpec.fit((0.05, 0.05, 0.05), (0.25, 0.25, 0.25), 0.02)
    solver = MPMSolver(p, MATS[:1], grid, Scene(ground=GroundPlane(height=0.09)), SolverConfig(threads=2))
    for _ in range(5):
        solver.substep(1e-4)
    fused = solver.arrays.acc[0].numpy() + solver.arrays.acc[1].numpy()
    solver.launches.invalidate()
    for launch in solver.launches.p2g:
        launch.launch()
    fresh = solver.arrays.acc[0].numpy() + solver.arrays.acc[1].numpy()
    assert fused[..., 3].sum() > 0
    np.testing.assert_allclose(fused, fresh, rtol=1e-5, atol=1e-6 * np.abs(fresh).max())
    solver.close()


@pytest.mark.parametrize("delta", [1e-5, 3e-6, 1e-6])
def test_a_particle_at_its_stencils_far_edge_keeps_the_grid_finite(delta):
    """A particle ``delta`` of a cell inside the far edge of its stencil in every axis gives the corner
    node a mass of about (0.5 delta^2)^3 of its own: a float32 denormal at delta = 1e-6, whose
    reciprocal overflowed, so the node's velocity and then the particle turned NaN (a plasticine
    stretch diverged in its first frame). Such a node is empty: the free particle keeps its velocity."""
    dx = 0.01
    p = Particles(x=np.full((1, 3), (5 + 1.5 - delta) * dx), volume=1e-7, material=0)
    p.v = np.array([[0.1, -0.2, 0.3]])
    grid = GridSpec((0.0, 0.0, 0.0), dx, (12, 12, 12))
    solver = MPMSolver(p, MATS[:1], grid, Scene(gravity=(0.0, 0.0, 0.0)), SolverConfig(threads=1))
    for _ in range(3):
        solver.substep(1e-5)
    assert np.isfinite(solver.grid_v.numpy()).all()
    s = solver.state()
    np.testing.assert_allclose(s.v, p.v, rtol=1e-5)
    np.testing.assert_allclose(s.F, np.eye(3)[None], atol=1e-6)


def test_particles_thrown_at_the_walls_stop_at_the_separating_walls():
    p = random_block(300, seed=2)
    p.v = np.tile([40.0, -30.0, 25.0], (300, 1))  # thrown hard at three walls
    grid = GridSpec.fit((0.05, 0.05, 0.05), (0.25, 0.25, 0.25), 0.025)
    water = MaterialParams("fluid", 1e5, 0.3, 1000.0)  # splashes against the walls instead of crushing
    solver = MPMSolver(p, [water], grid, Scene(gravity=(0, 0, 0)), SolverConfig(frame_dt=0.02))
    for _ in range(3):
        solver.step_frame()
    s = solver.state()
    lo, hi = np.asarray(grid.origin), np.asarray(grid.upper)
    assert np.isfinite(s.x).all() and np.isfinite(s.F).all()
    # Particles move with the grid velocity, which the walls 3 cells inside the faces stop; a
    # particle 2 cells in still reaches a free node with its stencil, so splashing water creeps a
    # little further (1.90 cells, measured). Before the fluid's pressure kept growing under
    # compression, all 300 particles lay crushed at J = 0.05 against the walls, at 2.00 cells.
    assert np.all(s.x >= lo + 1.5 * grid.dx) and np.all(s.x <= hi - 1.5 * grid.dx)
    assert np.linalg.det(s.F).min() > 0.1  # splashed, not crushed
    assert solver.escaped == 0 and not s.escaped.any()


def test_particles_driven_into_a_face_are_clamped_and_counted():
    p = random_block(300, seed=2)
    grid = GridSpec.fit((0.05, 0.05, 0.05), (0.25, 0.25, 0.25), 0.025)
    # A velocity box carries its particles past the walls; only the clamp at the face stops them.
    push = VelocityBox((0.09, 0.09, 0.09), (0.21, 0.21, 0.21), velocity=(8.0, 0.0, 0.0))
    solver = MPMSolver(
        p, MATS[:1], grid, Scene(gravity=(0, 0, 0), boxes=(push,)), SolverConfig(frame_dt=0.02)
    )
    for _ in range(2):
        solver.step_frame()
    s = solver.state()
    hi = np.asarray(grid.upper)
    assert np.isfinite(s.x).all() and np.all(s.x <= hi - grid.dx + 1e-6)
    assert solver.escaped == int(s.escaped.sum()) > 0


class NaNOnce:
    """Grid hook poisoning the velocity grid during the first ``times`` frames' first attempt."""

    def __init__(self, times: int) -> None:
        self.times = times
        self.calls = 0

    def apply(self, solver, dt):
        if solver.time < 1e-12 and self.times > 0:
            self.times -= 1
            g = solver.grid_v.numpy()
            g[..., 0] = np.nan
            solver.grid_v.assign(g)


def test_divergence_guard_restores_and_retries():
    p = random_block(100, seed=4)
    grid = GridSpec.fit((0.1, 0.1, 0.1), (0.2, 0.2, 0.2), 0.025)
    solver = MPMSolver(p, MATS[:1], grid, Scene(), SolverConfig(frame_dt=0.01))
    solver.hooks.append(NaNOnce(times=1))
    stats = solver.step_frame()
    assert stats.retries == 1 and stats.cfl == pytest.approx(0.5 * SolverConfig().cfl)
    assert np.isfinite(solver.state().x).all()


def test_divergence_guard_raises_instead_of_returning_nan():
    p = random_block(100, seed=5)
    grid = GridSpec.fit((0.1, 0.1, 0.1), (0.2, 0.2, 0.2), 0.025)
    solver = MPMSolver(p, MATS[:1], grid, Scene(), SolverConfig(frame_dt=0.01, max_retries=2))
    solver.hooks.append(NaNOnce(times=10))
    with pytest.raises(SimulationDiverged, match="non-finite"):
        solver.step_frame()


class InvertOnce:
    """Grid hook that, in the first sub-step of the first ``times`` attempts of frame 0, sets the grid
    velocity to the converging affine field -k (x - c) with k dt = 1.2: every particle's F is
    multiplied by (1 - k dt) = -0.2, an inversion with det F = -0.008 det F (inside the old guard's
    accepted range down to -0.5)."""

    def __init__(self, times: int) -> None:
        self.times = times

    def apply(self, solver, dt):
        if solver.time > 1e-12 or self.times <= 0:
            return
        self.times -= 1
        g = to_dense(solver.grid_v.numpy(), solver.grid.res)
        idx = np.stack(np.meshgrid(*[np.arange(n) for n in g.shape[:3]], indexing="ij"), axis=-1)
        pos = np.asarray(solver.grid.origin) + idx * solver.grid.dx
        centre = solver.state().x.mean(0)
        vel = -1.2 / dt * (pos - centre)
        has_mass = g[..., 3] > 0
        g[..., 4:7] += np.where(has_mass[..., None], vel - g[..., 0:3], 0.0)
        g[..., 0:3] = np.where(has_mass[..., None], vel, g[..., 0:3])
        solver.grid_v.assign(from_dense(g, solver.grid.res))


@pytest.mark.parametrize("material", [MATS[0], MATS[1]], ids=["fixed_corotated", "drucker_prager"])
def test_divergence_guard_retries_a_step_that_inverts_particles(material):
    p = random_block(100, seed=4)
    grid = GridSpec.fit((0.05, 0.05, 0.05), (0.25, 0.25, 0.25), 0.025)
    solver = MPMSolver(p, [material], grid, Scene(gravity=(0, 0, 0)), SolverConfig(frame_dt=0.01))
    solver.hooks.append(InvertOnce(times=1))
    stats = solver.step_frame()
    # With the old j_min = -0.5 the inverted state (det F ~ -0.008) was accepted: retries == 0.
    assert stats.retries == 1 and stats.j_min > 0.0
    assert np.all(np.linalg.det(solver.state().F.astype(np.float64)) > 0.0)


def test_divergence_guard_names_the_floor_when_it_gives_up():
    p = random_block(100, seed=4)
    grid = GridSpec.fit((0.05, 0.05, 0.05), (0.25, 0.25, 0.25), 0.025)
    cfg = SolverConfig(frame_dt=0.01, max_retries=1)
    solver = MPMSolver(p, MATS[:1], grid, Scene(gravity=(0, 0, 0)), cfg)
    solver.hooks.append(InvertOnce(times=10))
    with pytest.raises(SimulationDiverged, match=r"det F floor \(fixed_corotated 0.0001;"):
        solver.step_frame()


def test_j_floor_is_per_model_and_never_below_zero():
    from physgm.sim.constitutive import MODELS

    assert all(m.j_floor >= 0.0 for m in MODELS.values())
    assert MODELS["fixed_corotated"].j_floor > 0.0  # its barrier's pressure is clamped near J = 0
    with pytest.raises(ValueError, match="j_min"):
        SolverConfig(j_min=-0.5)


def test_two_threads_match_one_thread():
    p = random_block(3000, seed=6, lo=0.1, hi=0.3)
    grid = GridSpec.fit((0.05, 0.05, 0.0), (0.35, 0.35, 0.35), 0.02)
    scene = Scene(ground=GroundPlane(0.05))
    states = []
    for threads in (1, 2):
        solver = MPMSolver(p, MATS, grid, scene, SolverConfig(threads=threads, frame_dt=0.01))
        assert solver.threads == threads
        solver.step_frame()
        states.append(solver.state())
        solver.close()
    np.testing.assert_allclose(states[0].x, states[1].x, atol=1e-6)
    np.testing.assert_allclose(states[0].v, states[1].v, atol=1e-4)


def test_state_comes_back_in_the_callers_order():
    p = random_block(500, seed=7)
    perm = np.random.default_rng(0).permutation(500)
    q = Particles(x=p.x[perm], volume=p.volume[perm], material=p.material[perm], v=p.v[perm], F=p.F[perm])
    grid = GridSpec.fit((0.1, 0.1, 0.1), (0.2, 0.2, 0.2), 0.025)
    out = []
    for particles in (p, q):
        solver = MPMSolver(particles, MATS[:1], grid, Scene(), SolverConfig(frame_dt=0.01))
        solver.step_frame()
        solver.step_frame()  # re-sorted at the frame boundary
        out.append(solver.state().x)
    np.testing.assert_allclose(out[0][perm], out[1], atol=1e-6)


def test_substeps_follow_the_cfl_bound():
    p = random_block(200, seed=8)
    p.v = np.zeros_like(p.v)
    p.F = None  # at rest and unstressed: |v|max stays 0
    grid = GridSpec.fit((0.1, 0.1, 0.1), (0.2, 0.2, 0.2), 0.025)
    mat = MaterialParams("fixed_corotated", 1e7, 0.3, 1000.0)
    solver = MPMSolver(p, [mat], grid, Scene(gravity=(0, 0, 0)), SolverConfig(frame_dt=0.01))
    stats = solver.step_frame()
    c = mat.wave_speed()
    assert stats.dt_max <= 0.4 * grid.dx / c * (1 + 1e-9)
    assert stats.substeps == int(np.ceil(0.01 / (0.4 * grid.dx / c) - 1e-9))
    # A fast particle shortens the step: dt <= cfl dx / (c + |v|max).
    solver.set_velocities(np.tile([0.0, 0.0, 20.0], (len(p), 1)))
    stats = solver.step_frame(0.001)
    assert stats.dt_max <= 0.4 * grid.dx / (c + 20.0) * (1 + 1e-9)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: Particles(x=np.zeros((0, 3)), volume=1.0, material=0), "no particles"),
        (lambda: Particles(x=np.array([[0.1, 0.1, np.nan]]), volume=1.0, material=0), "not finite"),
        (lambda: Particles(x=np.ones((2, 3)), volume=-1.0, material=0), "volumes"),
    ],
)
def test_bad_particles_are_rejected(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_bad_solver_inputs_are_rejected():
    grid = GridSpec.fit((0.1, 0.1, 0.1), (0.2, 0.2, 0.2), 0.025)
    inside = Particles(x=np.full((4, 3), 0.15), volume=1e-6, material=[0, 0, 1, 1])
    with pytest.raises(ValueError, match="material index 1"):
        MPMSolver(inside, MATS[:1], grid)
    outside = Particles(x=np.full((4, 3), 0.5), volume=1e-6, material=0)
    with pytest.raises(ValueError, match="outside the grid interior"):
        MPMSolver(outside, MATS[:1], grid)
    with pytest.raises(ValueError, match="dx"):
        GridSpec((0, 0, 0), 0.0, (10, 10, 10))


def test_runs_on_an_explicit_device():
    p = random_block(50, seed=9)
    grid = GridSpec.fit((0.1, 0.1, 0.1), (0.2, 0.2, 0.2), 0.025)
    solver = MPMSolver(p, MATS[:1], grid, Scene(), SolverConfig(frame_dt=0.005), device=wp.get_device("cpu"))
    traj = solver.run(2)
    assert traj.x.shape == (3, 50, 3) and traj.F.shape == (3, 50, 3, 3) and len(traj.stats) == 2


def test_run_solver_is_one_solver_run():
    p = random_block(50, seed=9)
    grid = GridSpec.fit((0.1, 0.1, 0.1), (0.2, 0.2, 0.2), 0.025)
    cfg = SolverConfig(frame_dt=0.005)
    solver = MPMSolver(p, MATS[:1], grid, Scene(), cfg)
    expected = solver.run(2)
    solver.close()
    traj = run_solver(p, MATS[:1], grid, Scene(), 2, cfg)
    assert np.abs(traj.x[-1] - traj.x[0]).max() > 1e-4  # gravity moved the block
    np.testing.assert_array_equal(traj.x, expected.x)
    np.testing.assert_array_equal(traj.F, expected.F)


def test_raw_substeps_follow_a_fast_object_across_the_grid():
    p = random_block(400, seed=10, lo=0.05, hi=0.1)
    p.F, p.v = None, np.tile([3.0, 0.0, 0.0], (400, 1))
    grid = GridSpec.fit((0.0, 0.0, 0.0), (0.5, 0.15, 0.15), 0.025)
    solver = MPMSolver(p, MATS[:1], grid, Scene(gravity=(0, 0, 0)))
    dt = solver.stable_dt()
    n = int(0.1 / dt)
    for _ in range(n):  # no step_frame: the active grid box must follow on its own
        solver.substep(dt)
    s = solver.state()
    np.testing.assert_allclose(s.x[:, 0].mean() - p.x[:, 0].mean(), 3.0 * n * dt, rtol=1e-5)
    np.testing.assert_allclose(s.v.mean(0), [3.0, 0.0, 0.0], atol=1e-5)


def test_default_yaml_is_the_dataclass_default():
    assert SolverConfig.load("default") == SolverConfig()
    with pytest.raises(ValueError, match="unknown solver settings"):
        SolverConfig.from_dict({"cfl": 0.4, "clf": 0.3})
    with pytest.raises(ValueError, match="cfl=1.5"):
        SolverConfig(cfl=1.5)


@pytest.mark.gpu
def test_cuda_matches_cpu():
    p = random_block(500, seed=11)
    grid = GridSpec.fit((0.1, 0.1, 0.1), (0.2, 0.2, 0.2), 0.025)
    out = []
    for device in ("cpu", "cuda:0"):
        solver = MPMSolver(
            p, MATS, grid, Scene(ground=GroundPlane(0.1)), SolverConfig(frame_dt=0.01), device=device
        )
        solver.step_frame()
        out.append(solver.state().x)
    np.testing.assert_allclose(out[0], out[1], atol=1e-4)


def test_an_oversized_grid_is_refused_before_allocating():
    p = random_block(10, seed=12)
    huge = GridSpec((-10.0, -10.0, -10.0), 0.005, (4000, 4000, 4000))
    with pytest.raises(ValueError, match="max_grid_nodes"):
        MPMSolver(p, MATS[:1], huge)


def test_a_solver_started_from_another_ones_state_carries_on_as_it_would():
    """Particles(C=..., plastic=...) restores the whole state: a restart continues the run (the coasted
    flights of sim/coast.py resume this way); without C and the plastic history it does not."""
    p = random_block(400, seed=11, material=np.arange(400) % 2)
    grid = GridSpec.fit((0.05, 0.05, 0.0), (0.25, 0.25, 0.25), 0.02)
    scene = Scene(ground=GroundPlane(0.05))
    cfg = SolverConfig(frame_dt=0.005, threads=1)
    original = MPMSolver(p, MATS, grid, scene, cfg)
    original.step_frame()
    s = original.state()
    assert np.abs(s.plastic).max() > 0 and np.abs(s.C).max() > 0
    restarted = MPMSolver(
        Particles(s.x, p.volume, p.material, v=s.v, F=s.F, C=s.C, plastic=s.plastic), MATS, grid, scene, cfg
    )
    np.testing.assert_array_equal(restarted.state().C, s.C)
    # (the first stress evaluation re-applies the return mapping: equal to float32 rounding of a
    # strain of order one, 1.2e-7; measured 7e-8 with the fast-math kernels)
    np.testing.assert_allclose(restarted.state().plastic, s.plastic, rtol=1e-5, atol=2e-7)
    forgetful = MPMSolver(Particles(s.x, p.volume, p.material, v=s.v, F=s.F), MATS, grid, scene, cfg)
    runs = [solver.step_frame() and solver.state() for solver in (original, restarted, forgetful)]
    for solver in (original, restarted, forgetful):
        solver.close()
    same = np.abs(runs[1].x - runs[0].x).max()
    assert same < 1e-6
    assert np.abs(runs[2].x - runs[0].x).max() > 100 * max(same, 1e-8)


ONE_MODEL = [
    MaterialParams("fixed_corotated", 1e5, 0.3, 1000.0),
    MaterialParams("neo_hookean", 5e5, 0.45, 1100.0),
    MaterialParams("drucker_prager", 2e5, 0.3, 1500.0, friction_angle=30.0, cohesion=100.0),
    MaterialParams("mohr_coulomb", 2e5, 0.3, 1500.0, friction_angle=35.0),
    MaterialParams("von_mises", 1e6, 0.4, 1200.0, yield_stress=2e3, hardening=1e3),
    MaterialParams("foam", 1e5, 0.2, 100.0, yield_stress=500.0, hardening=100.0, viscosity=5.0),
    MaterialParams("fluid", 2e6, 0.3, 1000.0),
]


@pytest.mark.parametrize("material", ONE_MODEL, ids=lambda m: m.model)
def test_one_model_g2p_matches_the_switch_over_all_models(material):
    """A solver whose particles share one model runs a g2p compiled for that model's return
    mapping alone (``kernels.g2p_kernel``); it must step them as the switch over every model does,
    which a second, unused material of another model selects."""
    other = MaterialParams("fluid" if material.model != "fluid" else "fixed_corotated", 1e3, 0.3, 1000.0)
    grid = GridSpec((0.0, 0.0, 0.0), 0.025, (14, 12, 13))
    scene = Scene(ground=GroundPlane(height=0.11, friction=0.4))
    states, kernels = [], []
    for materials in ([material], [material, other]):
        solver = MPMSolver(random_block(200, seed=2), materials, grid, scene, SolverConfig(threads=1))
        for _ in range(3):
            solver.substep(solver.stable_dt())
        states.append(solver.state())
        kernels.append(solver._launches.g2p[0].kernel)
        solver.close()
    single, switch = states
    assert kernels[0] is not kernels[1]
    # The same arithmetic inlined or not: equal up to the contraction of a few multiply-adds.
    for name in ("x", "v", "C", "F", "plastic"):
        a, b = getattr(single, name), getattr(switch, name)
        scale = max(float(np.abs(b).max()), 1e-12)
        assert np.abs(a - b).max() <= 1e-5 * scale, f"{material.model}: {name} differs"
