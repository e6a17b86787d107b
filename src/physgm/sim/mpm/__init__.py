"""physgm.sim.mpm: the MLS-MPM engine in NVIDIA Warp (CPU and CUDA, one code path).

This docstring is the contract the Gaussian-level layer (``physgm.sim``: planner, rigid path,
coupling) and the benchmarks build on. Everything is SI: metres, seconds, kilograms, pascals.
World frame: +z up, ground z = 0.

Building blocks (all importable from ``physgm.sim.mpm``)
--------------------------------------------------------
``GridSpec(origin, dx, res)``                       (grid.py)
    Box grid, not necessarily cubic: ``origin`` (3,) m is node (0, 0, 0), ``dx`` the cell size,
    ``res = (nx, ny, nz)`` node counts (>= 8 each). ``GridSpec.fit(lo, hi, dx, margin_cells=3)``
    is the smallest grid whose free interior holds the box [lo, hi] (m); the planner fits it to
    the object's reachable region. ``grid.interior(cells)`` gives the region away from the faces.

``MaterialParams(model, E, nu, density, yield_stress=0, hardening=0, friction_angle=0,
cohesion=0, viscosity=0)``                          (``physgm.sim.constitutive``)
    Solver-level parameters of one material; validated (E > 0, -1 < nu < 0.5, density > 0,
    model extras) with a ValueError naming the bad value. ``get_material(name).params(E, nu)``
    builds one from the material table (``physgm.physics.materials``). ``.mu``, ``.lam``, ``.bulk``,
    ``.wave_speed()`` (P-wave speed, m/s). ``constitutive.MODELS``: the registry
    name -> ``ConstitutiveModel(id, stiffness, validate, plastic)``; models: fixed_corotated,
    neo_hookean, drucker_prager, mohr_coulomb (the table's sand), von_mises, foam, fluid.

``Particles(x [P, 3], volume [P] m^3, material [P] int, v=None [P, 3], F=None [P, 3, 3])``
    Input particle set (state.py), validated (P > 0, finite x, volume > 0). ``Particles.lattice
    (lo, hi, spacing, material, inside=None)`` and ``Particles.cat([...])`` help build scenes.
    ``ParticleState`` (x, v, F, C, plastic, escaped) is what ``solver.state()`` returns: numpy,
    in the caller's particle order (the solver sorts particles by cell internally).

``Scene(gravity=(0, 0, -9.81), ground=None, boxes=(), damping=0.0, walls=(), periodic=())``
(scene.py, boundary.py, walls.py)
    ``GroundPlane(height=0.0, friction=0.3, mode="separate"|"slip"|"sticky", held_depth=0.0,
    contact=None, stiffness=1.0, damping=0.2)``: on slip and Coulomb grounds (``contact=
    "particles"``, the default there) a penalty spring with a normal dashpot at each particle's
    material surface, half a particle spacing below it, with Coulomb friction on the particle
    (particle_ground.py): impacts begin and bodies rest at the plane, and the ground's force is
    reported as for the grid condition. Sticky grounds (and ``contact="nodes"``) act on grid nodes
    at or below the plane (bodies rest a cell high); ``held_depth=SURFACE_DEPTH`` (7/8 cell, on a
    grid the solver lowers by under a cell) makes light bodies touch and rest at the plane, with
    Coulomb friction also on the node layer at the surface (boundary.py, surface_friction.py).
    The implicit step always uses the node condition.
    ``VelocityBox(lo, hi, velocity, start=0, stop=inf, hold=True, axes=(True,) * 3, carry=True)``
    prescribes the velocity of grid nodes (and, with ``carry``, particles) inside a box that moves
    with it (grips, clamps with velocity 0, pushers); ``axes`` names the components it sets, and
    after ``stop`` a held box fixes them.
    ``damping`` (1/s) is a mass-proportional drag. ``SideWall(axis, position, solid="below"|
    "above", mode="slip"|"sticky")`` is a wall plane on x or y (or z); ``PeriodicAxis(axis, lo,
    hi)`` makes an axis periodic (lo, hi on grid nodes; plane-strain set-ups). The grid faces
    carry separating safety walls (``boundary_cells`` cells inside each face): every node update
    in which they stop mass is counted (``solver.face_contacts``, ``FrameStats.face_contacts``,
    the run report), a particle the final clamp has to hold is counted once in
    ``solver.escaped``, and no grid index can ever leave its array. A grid that holds the
    motion keeps both at 0 (the planner's grids do for its scenes).
    ``physgm.sim.scenes``: the ``SCENES`` registry and ``build_scene(name, x, material=None,
    **overrides) -> SceneSetup(scene, x, v, duration, reach_lo, reach_hi, driver_work)`` apply
    conf/sim/scene/<name>.yaml (drop, stretch, push, two_objects) to rest particles.

``SolverConfig`` (stepping.py; conf/sim/solver/default.yaml)
    frame_dt 0.04 s, cfl 0.4, flip 0.95 (affine-FLIP share of the particle (v, C) update, 0 = pure
    APIC; positions always move with the grid velocity), max_retries, j_min / j_max (divergence
    guard), boundary_cells, threads (0 = auto: 2 CPU threads from 500 particles, from 2k when it
    steps in Python), cfl_check_every, graphs (replay runs of sub-steps from captured launch graphs,
    one per thread), sort_every, max_substeps;
    integrator "explicit" | "pressure" | "implicit"; pressure_tolerance, pressure_max_iterations
    (the pressure split's solve), pressure_theta 0.6 (where in the sub-step it takes the volume
    term: 0.5 its middle to 1 its end); implicit_dt 0.01 s, implicit_theta 1.0 (the implicit step's
    settings, below).
    ``SolverConfig.load("default")`` reads the YAML.

``make_solver(particles, materials, grid, scene=None, config=None, device="cpu")`` (integrators.py)
    The solver class of ``config.integrator`` from the ``INTEGRATORS`` registry: ``MPMSolver``
    (explicit); ``PressureSplitMPMSolver`` (pressure.py: the elastic models fixed_corotated and
    neo_hookean with the first Lame parameter's volume term taken implicitly on the grid, a
    conjugate-gradient solve inside every sub-step, so the explicit step follows the shear part's
    wave: fewer sub-steps for nearly incompressible bodies; gravity and a ground with contact on
    the particles only, else a ValueError; ``solver.pressure.counters()``; docs/measurements_sim.md
    sections 29-31); or ``ImplicitMPMSolver`` (implicit.py: the same two models, gravity and a
    ground plane only, else a ValueError; sub-step implicit_dt while slow and cfl dx / |v|max when
    fast; Newton on the incremental potential, theta method with 1 = backward Euler, 0.5 = implicit
    midpoint; ``solver.implicit.log`` one ``SolveStats`` per sub-step; docs/measurements_sim.md
    section 10).

``MPMSolver(particles, materials, grid, scene=None, config=None, device="cpu")``  (solver.py)
    Allocates every array once, then only launches kernels.
    ``.step_frame(frame_dt=None) -> FrameStats``  CFL sub-steps (dt = cfl dx / (c_p + |v|max),
        |v|max re-read every ``cfl_check_every`` steps); checks the state (finite, J in
        (j_min, j_max], elastic trial J above each model's floor ``MODELS[m].j_floor``, so
        J <= 0 is a failed step); on failure restores the frame start and retries with half the CFL
        number, finally raises ``SimulationDiverged``. Never returns a NaN frame.
    ``.run(n_frames) -> Trajectory(x [T, P, 3], F [T, P, 3, 3], stats)``, frame 0 = initial.
    ``.substep(dt)``   one raw MLS-MPM step (no guard), for tests and couplings.
    ``.stable_dt()``, ``.state()``, ``.set_velocities(v [P, 3])``, ``.energy() -> Energy``
    (kinetic incl. APIC affine part, gravitational, elastic; J), ``.driver_work`` (J put in by
    velocity boxes), ``.time``, ``.frame``, ``.escaped``, ``.threads``, ``.close()``.
    ``.observers``: list of ``SubstepObserver``; ``observer.observe(SubstepObservables)`` runs
    after every sub-step with its time, dt, mass, momentum, centre-of-mass velocity and the
    forces of the ground, the side walls and the grid faces (observables.py;
    ``ObservableRecorder`` keeps them, dropping retried attempts). ``.face_contacts``.
    ``.hooks``: list of ``GridHook``; ``hook.apply(solver, dt)`` runs after each grid update.
    ``solver.grid_v`` is a wp.array4d [bx, by, bz, 64] of ``kernels.vec8`` in 4^3-node blocks
    (``grid_layout``: ``load``, ``store``, ``to_dense``) = (vx, vy, vz, mass,
    dvx, dvy, dvz, grip: the friction impulse a held node leaves for the surface layer, 0 unless
    the ground is held at depth); a hook that changes a node velocity must add the same change to
    components 4-6 (``kernels.set_node_velocity`` does both). Only nodes of the 4^3-node
    blocks a particle stencil reached this sub-step are current (``kernels.grid_update``);
    particles read no others.

``run_solver(particles, materials, grid, scene, n_frames, config=None, device="cpu")`` builds a
solver, runs it, closes it and returns the ``Trajectory``. Gaussians in, Gaussians out (plan,
sample particles, run, follow): ``physgm.sim.gaussian_trajectory.simulate``.

``cfl_dt(dx, materials, vmax, cfl)``, ``wave_speed(materials)`` and ``substeps_per_frame(...)``
predict the cost of a run before building a solver (for the planner).

Design notes (why the code looks the way it does)
-------------------------------------------------
* Two fused kernels per sub-step (kernels.py): grid_update, then g2p, which gathers the node
  velocities, updates F, runs the return mapping and the stress, moves the particle, clamps it,
  adds to the statistics, and scatters its mass, momentum and stress for the next sub-step.
  p2g (the same scatter from the stored state) runs only when the state is fresh: the first
  sub-step, a retried frame, new velocities. All are recorded once and replayed (launches.py).
  On the CPU, particles are split over two threads (a launch releases the GIL), each scattering
  into its own accumulator grid, and each thread updates half the grid; particles are re-sorted
  by cell every frame. g2p is compiled per set of constitutive models (``kernels.g2p_kernel``):
  a one-material scene runs its model's return mapping inlined.
* dt, time, the block stamp and the active box live in a device array, one row per CPU thread
  (substep_params.py), so the launches never change: without hooks, side walls, periodic axes or
  observers, each run of ``cfl_check_every`` sub-steps, and a frame's shorter tail as its binary
  pieces (8 + 4 + 1), is replayed from launch graphs captured once per thread
  (``wp.capture_begin``; Warp replays CPU graphs in C++; two threads meet at spin barriers inside
  them, spin_barrier.py), bit-identical to stepping in Python.
* grid_update only covers the active box around the particles (re-fitted every
  ``cfl_check_every`` steps); a particle that outruns it is flagged and the frame retried.
* The grid's node arrays lie in 4^3-node blocks of 64 consecutive nodes (grid_layout.py): a body
  spread thin reaches a few nodes of many blocks, and each block is then 2 KB in one piece, not
  16 rows a page apart. On the CPU they are lazily zeroed pages, so a grid sized for what a body
  may reach costs memory only where it goes, and grid_update runs a thread per slab of blocks
  across x, not one per block.
* The deformation state is H = F - I and every constitutive model works in H (b - I, det F - 1,
  log1p / expm1): stiff materials strain ~1e-5 per step, which float32 loses near 1.
* Particle updates blend APIC with an affine FLIP increment (``flip``): pure APIC loses energy
  per transfer; incrementing C with v keeps angular momentum exact.
* The ground's particle contact (particle_ground.py) is an external force in the scatter, as the
  stress force is, so the fused scatter stays independent of dt; its springs are no stiffer than
  the material (``stepping.step_wave_speed``: with 2 particles per cell axis the CFL step is
  unchanged), and its friction is capped by the springs' period, not by dt.
* Verification against analytic results: ``physgm.bench.verification`` (python -m physgm.bench
  sim-verify); the stiffness sweep: python -m physgm.bench sim-stability.
"""

from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm.boundary import GroundPlane, VelocityBox
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.implicit import ImplicitMPMSolver
from physgm.sim.mpm.integrators import INTEGRATORS, make_solver
from physgm.sim.mpm.pressure import PressureSplitMPMSolver
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.solver import GridHook, MPMSolver, run_solver
from physgm.sim.mpm.state import Energy, FrameStats, Particles, ParticleState, Trajectory
from physgm.sim.mpm.stepping import SimulationDiverged, SolverConfig, cfl_dt, substeps_per_frame, wave_speed
from physgm.sim.mpm.walls import PeriodicAxis, SideWall

__all__ = [
    "Energy",
    "FrameStats",
    "GridHook",
    "GridSpec",
    "GroundPlane",
    "INTEGRATORS",
    "ImplicitMPMSolver",
    "MPMSolver",
    "MaterialParams",
    "ParticleState",
    "Particles",
    "PeriodicAxis",
    "PressureSplitMPMSolver",
    "Scene",
    "SideWall",
    "SimulationDiverged",
    "SolverConfig",
    "Trajectory",
    "VelocityBox",
    "cfl_dt",
    "make_solver",
    "run_solver",
    "substeps_per_frame",
    "wave_speed",
]
