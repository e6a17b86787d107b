"""Sub-steps replayed from a captured launch graph (``SolverConfig.graphs``) against stepping in Python."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import numpy as np
import pytest
import warp as wp

from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm import GridSpec, GroundPlane, MPMSolver, Particles, Scene, SolverConfig, VelocityBox
from physgm.sim.mpm.boundary import SURFACE_DEPTH
from physgm.sim.mpm.spin_barrier import LIMIT_CYCLES, abandoned, barrier, new_counter

JELLY = MaterialParams("fixed_corotated", 1e5, 0.3, 1000.0)
SAND = MaterialParams("drucker_prager", 2e5, 0.3, 1500.0, friction_angle=30.0, cohesion=100.0)


def _drop(
    device: str, graphs: bool, scene: Scene, materials, frames: int = 3, threads: int = 1
) -> tuple[MPMSolver, int]:
    """A 500-particle block thrown sideways onto the ground: the solver after ``frames`` frames
    and the sub-steps it took."""
    rng = np.random.default_rng(3)
    x = rng.uniform((0.1, 0.1, 0.02), (0.18, 0.18, 0.1), (500, 3))
    p = Particles(x=x, volume=1e-6, material=np.arange(500) % len(materials))
    p.v = np.tile([0.4, 0.1, -0.5], (500, 1))
    grid = GridSpec.fit((0.05, 0.05, 0.0), (0.3, 0.25, 0.15), 0.01)
    config = SolverConfig(frame_dt=0.02, threads=threads, graphs=graphs)
    solver = MPMSolver(p, materials, grid, scene, config, device)
    steps = sum(solver.step_frame().substeps for _ in range(frames))
    return solver, steps


SCENES = {
    # held ground: the surface-friction launch is part of the graph; damping exercises exp(-k dt)
    "friction_ground": (
        Scene(ground=GroundPlane(0.0, friction=0.4, held_depth=SURFACE_DEPTH), damping=2.0),
        [JELLY],
    ),
    # contact on the particles: the contact forces are summed on the device into the ground impulse
    "particle_ground": (Scene(ground=GroundPlane(0.0, friction=0.4, contact="particles")), [JELLY]),
    # a velocity box that starts pushing mid-run: the kernels read time from the device clock
    "timed_box": (
        Scene(
            ground=GroundPlane(),
            boxes=(VelocityBox((0.0, 0.0, 0.0), (0.12, 0.3, 0.3), (0.3, 0, 0), start=0.012),),
        ),
        [JELLY, SAND],
    ),
}


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("name", sorted(SCENES))
def test_graph_replay_gives_the_same_particles_as_python_stepping(name, threads):
    """With two threads each replays its half's graph and they meet at spin barriers; the
    Python path hands off through a lock. Same kernels, same halves: the same bits."""
    scene, materials = SCENES[name]
    ref, steps = _drop("cpu", False, scene, materials, threads=threads)
    fast, fast_steps = _drop("cpu", True, scene, materials, threads=threads)
    assert ref.threads == fast.threads == threads
    assert ref.launches.replayed == 0 and fast_steps == steps
    # Every sub-step ran from a graph, the frame's tail too, but a frame's last one when
    # round-off makes it the shortened one (at most one in Python per frame).
    assert fast.launches.replayed >= steps - 3
    start = _drop("cpu", False, scene, materials, frames=0)[0].state().x
    a, b = ref.state(), fast.state()
    assert np.abs(a.x - start).max() > 0.02  # moved two cells: not a comparison of a still state
    for field in ("x", "v", "F", "C", "plastic"):  # same kernels in the same order: bit-identical
        np.testing.assert_array_equal(getattr(b, field), getattr(a, field), err_msg=field)
    assert fast.time == ref.time and fast.driver_work == ref.driver_work
    np.testing.assert_array_equal(fast.arrays.work.numpy(), ref.arrays.work.numpy())  # ground impulse too
    if name == "timed_box":
        assert ref.driver_work != 0.0  # the box acted (holding the block back: -6 mJ)
    ref.close()
    fast.close()


def test_graphs_are_not_used_with_observers():
    scene, materials = SCENES["friction_ground"]
    for threads in (1, 2):
        solver = _drop("cpu", True, scene, materials, frames=1, threads=threads)[0]
        assert solver.threads == threads and solver.launches.replayed > 0
        solver.observers.append(SimpleNamespace(observe=lambda obs: None))
        before = solver.launches.replayed
        solver.step_frame()
        assert solver.launches.replayed == before
        solver.close()


@pytest.mark.parametrize("threads", [1, 2])
def test_a_replay_leaves_the_particles_bounding_box_for_the_next_refit(threads):
    """Each thread's graph ends with the box of its particles; the solver's re-fit reads it
    instead of a pass over all particles, but only while nothing has stepped since."""
    scene, materials = SCENES["particle_ground"]
    solver = _drop("cpu", True, scene, materials, frames=1, threads=threads)[0]
    dt = solver.stable_dt()
    solver._substeps_graph(dt, 5)  # 4 + 1: the box comes from the last piece's graph
    x = solver.particles.x.numpy()
    lo, hi = solver.launches.replay_bounds()
    np.testing.assert_array_equal(lo, x.min(0))
    np.testing.assert_array_equal(hi, x.max(0))
    solver._fit_active(dt)
    replayed_box = [a.copy() for a in solver.active_box]
    solver.launches._box_stamp = None  # the same re-fit from the solver's own pass
    solver._fit_active(dt)
    for a, b in zip(replayed_box, solver.active_box, strict=True):
        np.testing.assert_array_equal(a, b)
    solver._substeps_graph(dt, 2)
    solver.substep(dt)  # a sub-step from Python: the box is stale
    assert solver.launches.replay_bounds() is None
    solver._substeps_graph(dt, 2)
    solver.launches.invalidate()  # a new state: stale too
    assert solver.launches.replay_bounds() is None
    solver.close()


@pytest.mark.gpu
def test_cuda_graph_replay_matches_python_stepping_on_cuda():
    scene, materials = SCENES["friction_ground"]
    ref = _drop("cuda:0", False, scene, materials)[0]
    fast = _drop("cuda:0", True, scene, materials)[0]
    assert fast.launches.replayed > 0
    # Atomic adds on a GPU sum in no fixed order, so two runs differ by round-off, which three
    # frames of contact can grow; a replay that skipped or repeated launches would move the block
    # by millimetres (dx = 1 cm).
    np.testing.assert_allclose(fast.state().x, ref.state().x, atol=2e-4)
    cpu = _drop("cpu", True, scene, materials)[0]
    np.testing.assert_allclose(fast.state().x, cpu.state().x, atol=1e-3)


def test_a_solver_in_a_worker_thread_steps_in_python():
    """A capture records every CPU launch of every thread, so only the main thread captures."""
    scene, materials = SCENES["friction_ground"]
    with ThreadPoolExecutor(1) as pool:
        solver, _ = pool.submit(_drop, "cpu", True, scene, materials, 1).result()
    assert solver.launches.replayed == 0
    solver.close()


def test_a_barrier_without_its_partner_gives_up_and_the_replay_raises():
    counter = new_counter("cpu")
    wp.launch(barrier, 1, [counter, 0, 1_000_000, 1_000], device="cpu")  # ~1 ms of cycles, nobody comes
    assert abandoned(counter)
    wp.launch(barrier, 1, [counter, 1, LIMIT_CYCLES, 1_000], device="cpu")  # abandoned: returns at once
    scene, materials = SCENES["friction_ground"]
    solver = _drop("cpu", True, scene, materials, frames=1, threads=2)[0]
    assert solver.launches.replayed > 0
    # A partner that died is seen only through the flag its barrier left; set it by hand.
    solver.launches._meeting.assign(np.array([0, 0, 0, 1], dtype=np.int64))
    with pytest.raises(RuntimeError, match="solver.threads=1"):
        solver.step_frame()
    solver.close()


def test_two_threads_from_fewer_particles_when_the_sub_steps_are_replayed():
    """Auto threads: 600 particles take two when graphs replay them (spin barriers), one when
    every sub-step would hand off through Python (no graphs, or a solver off the main thread)."""

    def solver(graphs: bool) -> MPMSolver:
        rng = np.random.default_rng(1)
        p = Particles(x=rng.uniform(0.1, 0.2, (600, 3)), volume=1e-6, material=0)
        grid = GridSpec.fit((0.05, 0.05, 0.05), (0.25, 0.25, 0.25), 0.02)
        return MPMSolver(p, [JELLY], grid, Scene(ground=GroundPlane(0.1)), SolverConfig(graphs=graphs))

    with ThreadPoolExecutor(1) as pool:
        off_main = pool.submit(solver, True).result()
    chosen = [solver(True), solver(False), off_main]
    assert [s.threads for s in chosen] == [2, 1, 1]
    for s in chosen:
        s.close()
