"""``simulate(gaussians, physics, scene, cameras)``: plan, execute, and move the Gaussians.

The one entry the rest of physgm calls. Steps: choose the grid and particle spacing from the
object size, sample particles from the Gaussians, build the scene (initial velocities,
boundaries), plan (rigid / MPM with capped E / MPM), then run either the rigid-body path or the
Warp MPM solver (``mpm_run``: flights in closed form where only gravity acts, early stop once
everything is still). The result holds particle positions and deformation gradients per frame;
deformed Gaussians are computed per frame on request.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace

import numpy as np
import torch

from physgm.cameras import Cameras
from physgm.gaussians import Gaussians
from physgm.physics.materials import PhysicsSpec, get_material
from physgm.sim.coast import ballistic_frames
from physgm.sim.constitutive import MaterialParams
from physgm.sim.coupling import follow_and_deform, rigid_transform_gaussians
from physgm.sim.mpm.implicit import IMPLICIT_PASSES_MIN
from physgm.sim.mpm.pressure import PRESSURE_STEP_COST
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.stepping import SolverConfig
from physgm.sim.mpm_run import run_mpm
from physgm.sim.planner import Plan, PlannerConfig, choose_spacing, plan_simulation, stretch_splits
from physgm.sim.rigid import ContactParams, RigidBody, RigidSimulator, RigidTrajectory
from physgm.sim.sampling import (
    Followers,
    ParticleSample,
    build_followers,
    mass_opacity,
    sample_particles,
    split_along,
)
from physgm.sim.scenes import SceneSetup, build_scene


@dataclass
class GaussianTrajectory:
    """A planned, executed simulation of Gaussians.

    Attributes:
        plan: what was simulated and why.
        gaussians: [N] rest Gaussians.
        particles: [P] rest simulation particles.
        followers: how each Gaussian follows the particles.
        x: [T, P, 3] particle positions per frame, m (frame 0 = rest).
        F: [T, P, 3, 3] particle (elastic) deformation gradients per frame.
        rigid: rigid poses per frame when plan.mode == "rigid", else None.
        rest_frame: first held frame after early stop (None: moved until the end).
        ballistic_frames: leading frames computed in closed form (free fall), not simulated.
        substeps: MPM sub-steps (or rigid steps) actually taken.
        seconds: wall-clock time of planning + simulation, s.
        plan_seconds: the part of ``seconds`` spent sampling particles and planning, s.
        face_contacts: grid-node updates in which the grid faces' safety walls stopped mass
            (``MPMSolver.face_contacts``); 0 when the planned grid held the motion.
        coasted_frames: frames of flights after a bounce computed in closed form (``sim.coast``).
        coast_predicted_px: the largest predicted error of those flights, pixels (within the bound
            left over by ``plan.predicted_error_px``).
        grid_moves: times the grid moved under a body that left the planned region
            (``mpm_run.followed_grid``).
    """

    plan: Plan
    gaussians: Gaussians
    particles: ParticleSample
    followers: Followers | None
    x: np.ndarray
    F: np.ndarray
    rigid: RigidTrajectory | None
    rest_frame: int | None
    ballistic_frames: int
    substeps: int
    seconds: float
    plan_seconds: float = 0.0
    face_contacts: int = 0
    coasted_frames: int = 0
    coast_predicted_px: float = 0.0
    grid_moves: int = 0

    def __len__(self) -> int:
        return self.x.shape[0]

    def gaussians_at(self, t: int) -> Gaussians:
        """Deformed Gaussians at frame t."""
        if self.rigid is not None:
            rot = torch.from_numpy(self.rigid.rotations[t]).float()
            com0 = torch.from_numpy(self.rigid.rest_com).float()
            shift = torch.from_numpy(self.rigid.coms[t]).float() - com0
            return rigid_transform_gaussians(self.gaussians, rot, shift, com0)
        return follow_and_deform(
            self.gaussians, self.followers, torch.from_numpy(self.x[t]), torch.from_numpy(self.F[t])
        )

    def reordered(self, index: torch.Tensor) -> GaussianTrajectory:
        """The same motion with the Gaussians in the order ``index`` [N] (a permutation) gives."""
        followers = self.followers
        if followers is not None:
            followers = Followers(followers.index[index], followers.weight[index], followers.offset[index])
        return replace(self, gaussians=self.gaussians[index], followers=followers)

    def frames(self) -> Iterator[Gaussians]:
        for t in range(len(self)):
            yield self.gaussians_at(t)

    def means(self) -> torch.Tensor:
        """Gaussian centres per frame, [T, N, 3] m (cheap: no covariance decomposition)."""
        if self.rigid is not None:
            rest = self.gaussians.means.detach().double().cpu().numpy()
            return torch.from_numpy(
                np.stack([self.rigid.transform(rest, t) for t in range(len(self))])
            ).float()
        x = torch.from_numpy(self.x)
        return torch.stack(
            [self.followers.apply(x[t], torch.from_numpy(self.F[t]))[0] for t in range(len(self))]
        )


def physics_params(physics: PhysicsSpec | MaterialParams) -> tuple[str, MaterialParams, float | None]:
    """(material name, solver parameters, rigid-path restitution or None) of the physics to simulate.

    ``MaterialParams`` is simulated as given (name "custom"). A JSON-shaped description
    (physical.json) becomes a ``PhysicsSpec`` with ``PhysicsSpec.from_dict`` first.
    """
    if isinstance(physics, MaterialParams):
        return "custom", physics, None
    if isinstance(physics, PhysicsSpec):
        return physics.material, physics.params(), physics.restitution
    raise TypeError(
        f"physics must be a PhysicsSpec (physgm.physics.materials) or MaterialParams, got "
        f"{type(physics).__name__}; a JSON-shaped description goes through PhysicsSpec.from_dict"
    )


def apply_scene(scene, x: np.ndarray, overrides: dict | None, surface: float = 0.0) -> SceneSetup:
    """The scene applied to rest particles x [P, 3]: placed particles, velocities, boundaries.

    ``scene`` is a registered scene name (conf/sim/scene; it may move the object, e.g. "drop"
    lifts it to its drop height), a ``SceneSetup``, a ``Scene`` (object left where it is, at rest)
    or a (Scene, v0 [P, 3] or [3]) pair. ``surface``: how far the material reaches below a particle
    centre, m (half the particle spacing): a registered scene places the material, not the centres.
    """
    if isinstance(scene, str):
        return build_scene(scene, x, surface=surface, **(overrides or {}))
    if overrides:
        raise ValueError("scene_overrides only apply to a registered scene given by name")
    if isinstance(scene, SceneSetup):
        return scene
    v0 = np.zeros_like(x)
    if isinstance(scene, tuple):
        scene, v = scene
        v0 = np.broadcast_to(np.asarray(v, dtype=np.float64), x.shape).copy()
    if not isinstance(scene, Scene):
        raise TypeError(
            f"scene must be a scene name, Scene, SceneSetup or (Scene, v0), got {type(scene).__name__}"
        )
    inf = np.full(3, np.inf)
    return SceneSetup(scene, x, v0, duration=math.inf, reach_lo=-inf, reach_hi=inf)


def _place_gaussians(gaussians: Gaussians, x_rest: torch.Tensor, x_placed: np.ndarray) -> Gaussians:
    """Gaussians moved the way the scene moved the particles (a translation per object)."""
    shift = x_placed - x_rest.double().numpy()  # [P, 3]
    if np.abs(shift).max() == 0.0:
        return gaussians
    if np.ptp(shift, axis=0).max() < 1e-9:
        delta = torch.from_numpy(shift[0]).to(gaussians.means)
    else:  # several objects placed apart: each Gaussian moves with its nearest particle
        nearest = build_followers(gaussians.means, x_rest, k=1)
        delta = torch.from_numpy(shift).to(gaussians.means)[nearest.index[:, 0]]
    return replace(gaussians, means=gaussians.means + delta)


@dataclass
class PreparedSimulation:
    """Everything ``simulate`` settles before the solver starts: the plan and what it runs on.

    ``plan.predicted_cost`` and ``ballistic_frames`` let a caller decide, before any solver
    step, whether the run fits a time budget (``physgm.train.rollout_budget``).
    """

    plan: Plan
    gaussians: Gaussians  # [N] placed where the scene starts
    sample: ParticleSample  # [P] placed particles
    scene: Scene
    v0: np.ndarray  # [P, 3] m/s
    material: MaterialParams  # at the requested E (the plan says which E runs)
    planner: PlannerConfig
    solver: SolverConfig
    seconds: float  # sampling + planning, s
    mass_opacity: float  # Gaussians at least this opaque carry mass (sampling.mass_opacity)

    @property
    def ballistic_frames(self) -> int:
        """Leading frames computed in closed form (1 without the ballistic prefix)."""
        if self.plan.mode == "rigid" or not self.planner.ballistic:
            return 1
        x0 = self.sample.x.detach().cpu().double().numpy()
        return ballistic_frames(
            x0, self.v0, self.scene, self.plan.frame_dt, self.plan.n_frames, 3 * self.plan.dx
        )

    def predicted_seconds(self, throughput: float) -> float:
        """Seconds the simulation should take at ``throughput`` MPM particle-substeps/s: the plan's
        cost over the frames after the closed-form prefix (0 for the rigid path, well under a second).
        An implicit sub-step counts as the fewest passes over the particles one was measured to take,
        a pressure-split one as ``pressure.PRESSURE_STEP_COST`` explicit ones."""
        plan = self.plan
        if plan.mode == "rigid":
            return 0.0
        simulated = max(plan.n_frames - self.ballistic_frames, 0) / max(plan.n_frames - 1, 1)
        passes = {"implicit": IMPLICIT_PASSES_MIN, "pressure": PRESSURE_STEP_COST}
        return plan.predicted_cost * passes.get(self.solver.integrator, 1) * simulated / throughput


def _check_tensile_limit(name: str, setup: SceneSetup) -> None:
    """Refuse a stretch past what the material survives (``Material.tensile_limit``).

    Fracture is not modelled, so a ceramic mug pulled to twice its length would stretch like a
    rubber band, at the cost of hours of a ceramic's sub-steps (the step follows its wave speed)."""
    if setup.stretch is None or name == "custom":
        return
    limit = get_material(name).tensile_limit
    strain = setup.stretch[1] - 1.0
    if limit is None or strain <= limit:
        return
    raise ValueError(
        f"real {name} fails in tension at about {limit:.3g} strain, and this stretch pulls parts of it "
        f"to {strain:.3g}; fracture is not modelled, so the clip would show it drawn out like rubber "
        f"instead. Stretch it less (a scene ratio nearer 1), or take a material that stretches that "
        f"far (rubber, jelly, foam, fabric, leather, plasticine)"
    )


def prepare_simulation(
    gaussians: Gaussians,
    physics: PhysicsSpec | MaterialParams,
    scene: str | Scene | tuple,
    cameras: Cameras,
    n_frames: int = 50,
    planner: PlannerConfig | dict | None = None,
    solver: SolverConfig | None = None,
    scene_overrides: dict | None = None,
) -> PreparedSimulation:
    """Samples particles, applies the scene and plans: all of ``simulate`` before the solver starts.

    Args:
        gaussians: [N] object Gaussians in SI metres, +z up, placed where the scene starts.
        physics: a ``PhysicsSpec`` (material of the table, E, nu, density, restitution), or
            ``MaterialParams`` simulated as given.
        scene: registered scene name (conf/sim/scene), a Scene, a SceneSetup, or (Scene, v0 [P, 3]
            or [3]).
        cameras: output cameras and resolution (the pixel bound is measured there).
        n_frames: output frames T including the rest frame 0.
        planner: planner settings (conf/sim/planner/default.yaml).
        solver: MPM solver settings (frame_dt, cfl, ...).
        scene_overrides: keyword arguments of a registered scene (e.g. the drop's height, m).
    """
    start = time.perf_counter()
    cfg = PlannerConfig(**planner) if isinstance(planner, dict) else planner or PlannerConfig()
    solver_cfg = solver or SolverConfig()
    frame_dt = solver_cfg.frame_dt
    name, material, restitution = physics_params(physics)
    if restitution is not None:  # the material table has none; a physics description may
        cfg = replace(cfg, restitution=float(restitution))
    threshold = mass_opacity(gaussians.opacities, cfg.min_opacity, cfg.relative_opacity)
    opaque = gaussians.opacities >= threshold
    if not opaque.any():
        raise ValueError(f"no Gaussian has opacity >= {threshold:.3g}; nothing to simulate")
    extent = gaussians.means[opaque].detach().amax(0) - gaussians.means[opaque].detach().amin(0)
    dx, spacing = choose_spacing(float(extent.max()), cfg)
    rest = sample_particles(gaussians, spacing, threshold, cfg.fill_interior)
    # The lattice's material reaches half a spacing below each particle (sampling).
    surface = 0.5 * spacing
    setup = apply_scene(scene, rest.x.detach().cpu().double().numpy(), scene_overrides, surface)
    _check_tensile_limit(name, setup)
    if setup.stretch is not None and (splits := stretch_splits(setup.stretch[1], spacing, dx, cfg)) > 1:
        # The scene sees the particles it will pull (its grips are set from their extent).
        rest = split_along(rest, setup.stretch[0], splits)
        setup = apply_scene(scene, rest.x.detach().cpu().double().numpy(), scene_overrides, surface)
    gaussians = _place_gaussians(gaussians, rest.x.detach().cpu(), setup.x)
    sample = replace(rest, x=torch.from_numpy(setup.x).float().to(rest.x.device))
    v0 = np.asarray(setup.v, dtype=np.float64)
    plan = plan_simulation(
        sample.x.cpu(),
        sample.volume,
        torch.from_numpy(v0),
        name,
        material,
        setup.scene,
        cameras,
        n_frames,
        frame_dt,
        dx,
        spacing,
        cfg,
        solver_cfg.integrator,
        solver_cfg.implicit_dt,
    )
    if plan.integrator != solver_cfg.integrator:  # the planner took the pressure split
        solver_cfg = replace(solver_cfg, integrator=plan.integrator)
    return PreparedSimulation(
        plan,
        gaussians,
        sample,
        setup.scene,
        v0,
        material,
        cfg,
        solver_cfg,
        time.perf_counter() - start,
        threshold,
    )


def run_prepared(
    prepared: PreparedSimulation,
    device: str = "cpu",
    deadline: float | None = None,
    on_frame: Callable[[int, int], None] | None = None,
) -> GaussianTrajectory:
    """Run a prepared simulation; ``deadline`` (a ``time.perf_counter()`` value) cuts an MPM run
    between frames with ``mpm_run.SimulationBudgetExceeded``. ``on_frame(frames, substeps)`` hears
    how much of the clip is done (``mpm_run.run_mpm``; the rigid path calls it once, at the end)."""
    start = time.perf_counter() - prepared.seconds
    plan, sample, gaussians, cfg = prepared.plan, prepared.sample, prepared.gaussians, prepared.planner
    x0, v0, n_frames = sample.x.detach().cpu().double().numpy(), prepared.v0, plan.n_frames
    if plan.mode == "rigid":
        traj = _run_rigid(
            plan,
            prepared.scene,
            x0,
            v0,
            sample,
            prepared.material.density,
            gaussians,
            prepared.mass_opacity,
            cfg,
        )
        xs = np.stack([traj.transform(x0, t) for t in range(n_frames)]).astype(np.float32)
        Fs = np.broadcast_to(traj.rotations[:, None].astype(np.float32), (n_frames, len(x0), 3, 3))
        if on_frame is not None:
            on_frame(n_frames, traj.steps)
        seconds = time.perf_counter() - start
        return GaussianTrajectory(
            plan,
            gaussians,
            sample,
            None,
            xs,
            Fs,
            traj,
            traj.rest_frame,
            1,
            traj.steps,
            seconds,
            prepared.seconds,
        )
    followers = build_followers(gaussians.means, sample.x, k=cfg.follower_k)
    run = run_mpm(
        plan,
        prepared.material.with_elasticity(E=plan.E_used, nu=plan.nu_used),
        prepared.scene,
        x0,
        v0,
        sample,
        prepared.solver,
        device,
        cfg.ballistic,
        deadline,
        max(cfg.bound_px - plan.predicted_error_px, 0.0) if cfg.coast else 0.0,
        cfg.follow,
        on_frame,
    )
    seconds = time.perf_counter() - start
    return GaussianTrajectory(
        plan,
        gaussians,
        sample,
        followers,
        run.x,
        run.F,
        None,
        run.rest_frame,
        run.ballistic_frames,
        run.substeps,
        seconds,
        prepared.seconds,
        run.face_contacts,
        run.coasted_frames,
        run.coast_predicted_px,
        run.grid_moves,
    )


def simulate(
    gaussians: Gaussians,
    physics: PhysicsSpec | MaterialParams,
    scene: str | Scene | tuple,
    cameras: Cameras,
    *,
    device: str = "cpu",
    on_frame: Callable[[int, int], None] | None = None,
    **options,
) -> GaussianTrajectory:
    """Plans and runs the cheapest simulation that stays within the pixel bound.

    ``prepare_simulation`` then ``run_prepared``: the arguments and the ``options`` (n_frames,
    planner, solver, scene_overrides) are ``prepare_simulation``'s; ``device`` (the Warp device of
    the MPM solver) and ``on_frame`` are ``run_prepared``'s.
    """
    prepared = prepare_simulation(gaussians, physics, scene, cameras, **options)
    return run_prepared(prepared, device, on_frame=on_frame)


def _run_rigid(
    plan: Plan,
    scene: Scene,
    x0: np.ndarray,
    v0: np.ndarray,
    sample: ParticleSample,
    density: float,
    gaussians: Gaussians,
    min_opacity: float,  # the Gaussians at least this opaque are the contact hull's points
    cfg: PlannerConfig,
) -> RigidTrajectory:
    """Rigid path: mass and inertia from the particles, contacts on the visible Gaussians' hull."""
    mass = sample.volume.double().cpu().numpy() * density
    ground = scene.ground
    contact = ContactParams(
        restitution=plan.restitution,
        friction=ground.friction if ground is not None else 0.0,
        ground_height=None if ground is None else ground.height,
        walls=tuple(plan.walls),  # the scene's still walls, found by the planner
        gravity=tuple(scene.gravity),
    )
    surface = gaussians.means[gaussians.opacities >= min_opacity].detach().double().cpu().numpy()
    body = RigidBody.from_particles(x0, mass, contact_points=surface)
    sim = RigidSimulator(body, contact, RigidSimulator.initial_state(body, x0, mass, v0))
    rest_speed = plan.rest_px / plan.px_per_m / plan.frame_dt
    return sim.run(plan.n_frames, plan.frame_dt, cfg.rigid_dt, rest_speed, cfg.rest_frames)
