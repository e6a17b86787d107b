"""``simulate``: plan + execute end to end (small objects, few frames, CPU)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest
import torch

from physgm.bench.drop_scene import project
from physgm.cameras import orbit_cameras
from physgm.gaussians import Gaussians, quat_to_rotmat
from physgm.physics.materials import PhysicsSpec
from physgm.sim import mpm_run
from physgm.sim.gaussian_trajectory import ballistic_frames, prepare_simulation, run_prepared, simulate
from physgm.sim.mpm.boundary import GroundPlane
from physgm.sim.mpm.implicit import IMPLICIT_PASSES_MIN
from physgm.sim.mpm.pressure import PRESSURE_STEP_COST
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.stepping import SolverConfig
from physgm.sim.mpm_run import motion_left_px
from physgm.sim.planner import PlannerConfig

G = 9.81
CAMERAS = orbit_cameras(
    [30.0], [15.0], radius=0.8, fov_deg=40.0, width=256, height=256, target=(0.0, 0.0, 0.2)
)
GROUND = Scene(ground=GroundPlane(0.0, friction=0.4))


def _unit_box_surface(n: int, g: torch.Generator) -> torch.Tensor:  # [n, 3]
    """n points uniformly on the faces of the unit cube centred at the origin."""
    face = torch.randint(0, 6, (n,), generator=g)
    uv = torch.rand(n, 2, generator=g) - 0.5
    pts = torch.zeros(n, 3)
    for a in range(3):
        m = face // 2 == a
        others = [b for b in range(3) if b != a]
        pts[m, a] = 0.5 * ((face[m] % 2) * 2 - 1.0)
        pts[m, others[0]], pts[m, others[1]] = uv[m, 0], uv[m, 1]
    return pts


def _shell_cube(n: int = 3000, side: float = 0.1, bottom: float = 0.3, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    pts = _unit_box_surface(n, g)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    return Gaussians(
        means=pts * side + torch.tensor([0.0, 0.0, bottom + side / 2]),
        quats=quats,
        scales=torch.rand(n, 3, generator=g) * 0.002 + 0.001,
        opacities=torch.full((n,), 0.9),
        colors=torch.rand(n, 3, generator=g),
    )


def test_steel_drop_runs_rigid_and_moves_gaussians_rigidly():
    gs = _shell_cube()
    done = []
    traj = simulate(gs, PhysicsSpec("metal", E=2e11), GROUND, CAMERAS, n_frames=40, on_frame=_record(done))
    assert traj.plan.mode == "rigid"
    assert len(traj) == 40 and done == [(40, traj.substeps)]  # the rigid path reports once, at the end
    # Falls 0.3 m: the bottom reaches the ground, and the body never sinks below it.
    assert traj.x[:, :, 2].min() > -1e-3
    # The Gaussians touch the ground; the particles sit at voxel centres, half a spacing inside.
    assert float(traj.means()[-1, :, 2].min()) == pytest.approx(0.0, abs=2e-3)
    assert traj.x[-1, :, 2].min() == pytest.approx(0.5 * traj.particles.spacing, abs=2e-3)
    g10 = traj.gaussians_at(10)
    rot = torch.from_numpy(traj.rigid.rotations[10]).float()
    torch.testing.assert_close(g10.scales, gs.scales)
    torch.testing.assert_close(quat_to_rotmat(g10.quats), rot @ quat_to_rotmat(gs.quats), atol=1e-5, rtol=0)
    # Held at rest after it settles.
    assert traj.rest_frame is not None
    np.testing.assert_array_equal(traj.x[traj.rest_frame], traj.x[-1])


def test_ballistic_frames_match_free_fall_time():
    x = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.6]])
    k = ballistic_frames(x, np.zeros_like(x), GROUND, frame_dt=0.04, n_frames=50, gap=0.01)
    t_hit = math.sqrt(2 * 0.49 / G)
    assert (k - 1) * 0.04 <= t_hit < k * 0.04
    # Non-uniform initial velocity (a spin) is not a free rigid translation: no shortcut.
    spin = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    assert ballistic_frames(x, spin, GROUND, 0.04, 50, 0.01) == 1


def test_jelly_drop_runs_mpm_and_gaussians_follow_particles():
    gs = _shell_cube(bottom=0.05)
    cfg = PlannerConfig(cells_across=8)
    traj = simulate(gs, PhysicsSpec("jelly", E=3e4), GROUND, CAMERAS, n_frames=8, planner=cfg)
    plan = traj.plan
    assert plan.mode == "mpm" and plan.E_used == 3e4
    assert traj.substeps > 0 and traj.ballistic_frames >= 1
    # Ballistic prefix is exact free fall; after it the solver takes over.
    for k in range(traj.ballistic_frames):
        t = k * 0.04
        np.testing.assert_allclose(traj.x[k], traj.x[0] + np.array([0, 0, -0.5 * G * t * t]), atol=1e-6)
    # Everything stays above the ground (within a cell) and the object squashes on impact.
    assert traj.x[:, :, 2].min() > -plan.dx
    # Gaussians follow the particles: centres from the follower interpolation.
    last = traj.gaussians_at(len(traj) - 1)
    assert torch.isfinite(last.means).all() and torch.isfinite(last.quats).all()
    assert (last.means[:, 2] - traj.x[-1][:, 2].min()).min() > -plan.dx
    assert float(last.means[:, 2].mean()) < float(gs.means[:, 2].mean()) - 0.02
    assert traj.face_contacts == traj.grid_moves == 0  # the planned grid held the motion


def test_planned_grid_holds_a_sand_collapse():
    """Sand dropped onto the floor runs out; the planner's grid must hold it off the grid faces."""
    gs = _shell_cube(bottom=0.1)
    cfg = PlannerConfig(cells_across=8, particles_per_cell=1)  # coarse: the extent is the point
    traj = simulate(gs, PhysicsSpec("sand"), GROUND, CAMERAS, n_frames=30, planner=cfg)
    assert traj.plan.mode == "mpm"
    spread = np.abs(traj.x[-1, :, :2] - traj.x[0, :, :2].mean(0)).max()
    assert spread > 0.1  # it did collapse and run out (the cube's half size is 0.05 m)
    assert traj.face_contacts == traj.grid_moves == 0


def _leaning_slab(n: int = 4000, dims=(0.04, 0.05, 0.3), lean_deg: float = 20.0) -> Gaussians:
    """Gaussians on the surface of a tall slab standing on the ground, leaning toward -y."""
    g = torch.Generator().manual_seed(0)
    pts = _unit_box_surface(n, g)
    t = math.radians(lean_deg)
    rot = torch.tensor([[1.0, 0.0, 0.0], [0.0, math.cos(t), -math.sin(t)], [0.0, math.sin(t), math.cos(t)]])
    pts = (pts * torch.tensor(dims)) @ rot.T
    pts[:, 2] -= pts[:, 2].min() - 0.002
    return Gaussians(
        means=pts,
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        scales=torch.full((n, 3), 0.0015),
        opacities=torch.full((n,), 0.9),
        colors=torch.rand(n, 3, generator=g),
    )


def test_planned_grid_holds_a_slab_that_falls_over():
    """A 0.3 m slab leaning past its tipping angle falls flat about its base edge. Tumbling about
    its centre reaches 0.15 m; lying down it reaches 0.26 m, and before the toppling margin the
    grid's face walls held it up at 0.23 m."""
    traj = simulate(
        _leaning_slab(), PhysicsSpec("jelly", E=1e5), GROUND, CAMERAS, n_frames=25,
        planner=PlannerConfig(cells_across=8, follow=False),  # the planned grid alone
    )  # fmt: skip
    assert traj.plan.mode == "mpm"
    assert traj.x[-1, :, 2].max() < 0.08  # it lies flat (it stood 0.3 m tall)
    assert traj.x[-1, :, 1].min() < -0.24  # out past where the walls used to stop it
    assert traj.face_contacts == 0


def test_early_stop_holds_frames_once_still():
    # A block pushed along the ground: friction stops it within a few frames, then it is held.
    gs = _shell_cube(bottom=0.0)
    # One particle per cell is enough to test early stopping, and 8x cheaper than the default 8.
    cfg = PlannerConfig(
        cells_across=8, particles_per_cell=1, allow_rigid=False, allow_stiffness_cap=False, rest_frames=3
    )
    physics = PhysicsSpec("rubber", E=1e6, nu=0.3)
    done = []  # (frames, sub-steps) as the run reports them
    traj = simulate(
        gs, physics, (GROUND, [0.3, 0.0, 0.0]), CAMERAS, n_frames=30, planner=cfg, on_frame=_record(done)
    )
    assert traj.plan.mode == "mpm"
    moved_px = np.linalg.norm(np.diff(traj.x, axis=0), axis=2).max(axis=1) * traj.plan.px_per_m  # [T-1]
    assert moved_px[0] > 1.0  # it visibly slides first
    assert traj.rest_frame is not None and traj.rest_frame < 30
    # The last simulated frames were still; every later frame repeats the last simulated one.
    assert (moved_px[traj.rest_frame - 1 - cfg.rest_frames : traj.rest_frame - 1] < cfg.rest_px).all()
    for k in range(traj.rest_frame, 30):
        np.testing.assert_array_equal(traj.x[k], traj.x[traj.rest_frame - 1])
    # The held frames cost nothing: fewer sub-steps than planned for the whole clip.
    assert traj.substeps < traj.plan.substeps_per_frame * 29 * 0.8
    # The progress reported: frame by frame up to the rest frame, then the held rest at once.
    _check_progress(done, traj)
    assert [f for f, _ in done[-3:]] == [traj.rest_frame - 2, traj.rest_frame - 1, 30]
    assert traj.face_contacts == traj.grid_moves == 0  # the slide stayed inside the planned grid


def test_held_frames_stay_within_the_rest_budget_of_the_unstopped_run():
    # A block slides on a frictionless floor under air drag: its motion decays by 0.82 a frame and
    # never stops, so only the budget on the extrapolated creep decides when the frames are held.
    scene = Scene(ground=GroundPlane(0.0, friction=0.0), damping=5.0)
    gs, physics = _shell_cube(bottom=0.0), PhysicsSpec("rubber", E=1e6, nu=0.3)
    base = dict(cells_across=8, particles_per_cell=1, allow_rigid=False, allow_stiffness_cap=False)

    def slide(**planner):
        return simulate(
            gs,
            physics,
            (scene, [0.3, 0.0, 0.0]),
            CAMERAS,
            n_frames=40,
            planner=PlannerConfig(**base, **planner),
        )

    full = slide(rest_frames=10**6)
    assert full.rest_frame is None
    stops = []
    for budget in (0.1, 0.03):  # measured: held at frames 29 and 34, 0.091 and 0.027 px from the full run
        traj = slide(rest_budget_px=budget)
        k = traj.rest_frame
        np.testing.assert_array_equal(full.x[:k], traj.x[:k])
        held_px = np.linalg.norm(full.x[k:] - traj.x[k:], axis=2).max() * traj.plan.px_per_m
        assert budget / 3 < held_px < budget, (budget, held_px)
        stops.append(k)
    assert stops[0] < stops[1]


def test_motion_left_continues_the_fitted_decay():
    # Halving every frame: 0.0625 px in the last frame, then 1/32 + 1/64 + 1/128 over three more.
    assert motion_left_px([1.0, 0.5, 0.25, 0.125, 0.0625], 3) == pytest.approx(0.0625 * 0.875)
    # A steady slide or a growing motion goes on at the last frame's pace.
    assert motion_left_px([0.04] * 5, 10) == pytest.approx(0.4)
    assert motion_left_px([0.01, 0.02, 0.03, 0.04, 0.05], 10) == pytest.approx(0.5)
    assert motion_left_px([0.1, 0.05], 0) == 0.0


def test_physics_spec_reads_table_and_overrides():
    from physgm.sim.constitutive import MaterialParams
    from physgm.sim.gaussian_trajectory import physics_params

    spec = PhysicsSpec.from_dict({"material": "rubber", "E": 2e6, "nu": 0.45, "density": 1200.0})
    assert PhysicsSpec.from_dict(spec.to_dict()) == spec
    name, params, restitution = physics_params(spec)
    assert name == "rubber" and params.model == "neo_hookean" and restitution is None
    assert (params.E, params.nu, params.density) == (2e6, 0.45, 1200.0)
    name, params, _ = physics_params(PhysicsSpec("metal"))  # table defaults
    assert params.yield_stress > 0 and params.E == pytest.approx(2e11)
    custom = MaterialParams("fixed_corotated", 1e5, 0.3, 1000.0)
    assert physics_params(custom) == ("custom", custom, None)  # simulated as given
    with pytest.raises(ValueError, match="material"):
        PhysicsSpec.from_dict({"E": 1e6})
    with pytest.raises(ValueError, match="takes only"):
        PhysicsSpec.from_dict({"material": "metal", "young": 1e6})  # a misspelt key is not ignored
    with pytest.raises(ValueError, match="unknown material"):
        PhysicsSpec("unobtainium")
    with pytest.raises(TypeError, match="PhysicsSpec.from_dict"):
        physics_params({"material": "metal", "E": 1e6})  # JSON goes through from_dict first
    with pytest.raises(TypeError, match="PhysicsSpec"):
        physics_params(("metal", 1e6))


def test_registered_drop_scene_places_object_and_gaussians():
    gs = _shell_cube(bottom=0.0)
    traj = simulate(gs, PhysicsSpec("ceramic"), "drop", CAMERAS, n_frames=5, scene_overrides={"height": 0.2})
    assert traj.plan.mode == "rigid"
    first = traj.gaussians_at(0)
    # Lifted so the material's lowest surface, half a spacing under the lowest particles, is 0.2 m
    # above the ground; the Gaussians moved with it.
    spacing = traj.particles.spacing
    assert traj.x[0, :, 2].min() - 0.5 * spacing == pytest.approx(0.2, abs=1e-6)
    shift = first.means - gs.means
    torch.testing.assert_close(shift, shift[:1].expand_as(shift), atol=1e-6, rtol=0)
    # The bottom face Gaussians started at z = 0, on the lattice's lowest surface: now 0.2 m up.
    assert float(shift[0, 2]) == pytest.approx(0.2, abs=1e-6)
    with pytest.raises(ValueError, match="overrides"):
        simulate(gs, PhysicsSpec("ceramic"), GROUND, CAMERAS, n_frames=5, scene_overrides={"height": 0.2})


def test_a_body_set_on_the_ground_rests_there_on_the_rigid_path_and_in_mpm():
    # A stiff cube set on the ground (drop height 0): the rigid path and MPM at full stiffness must
    # rest it in the same place, its lowest Gaussians on the plane. Before the scenes placed the
    # material's surface, MPM rested it half a particle spacing deeper, 0.76 px off the rigid path
    # at 256 px (docs/measurements_sim.md section 32).
    gs = _shell_cube(bottom=0.0)
    physics = PhysicsSpec("plastic", E=1e8)
    kw = dict(n_frames=4, scene_overrides={"height": 0.0})
    rigid = simulate(gs, physics, "drop", CAMERAS, **kw)
    mpm = simulate(gs, physics, "drop", CAMERAS, planner=PlannerConfig(allow_rigid=False), **kw)
    assert (rigid.plan.mode, mpm.plan.mode) == ("rigid", "mpm")
    for traj in (rigid, mpm):
        assert float(traj.means()[-1, :, 2].min()) == pytest.approx(0.0, abs=2e-4)
    # Measured: 0.06-0.13 px a frame apart (0.87-0.93 px before), the lowest Gaussian 0.09 mm
    # under the plane in MPM (2.2 mm before).
    assert float((_pixels(rigid) - _pixels(mpm)).norm(dim=-1).mean(-1).max()) < 0.25


def _pixels(traj) -> torch.Tensor:
    """Projected Gaussian centres [T, N, 2] in the test camera."""
    return project(CAMERAS, traj.means())


def _record(done: list) -> Callable[[int, int], None]:
    return lambda frames, substeps: done.append((frames, substeps))


def _check_progress(done: list[tuple[int, int]], traj) -> None:
    """``on_frame`` reports: the closed-form prefix first, never backwards, the whole clip last."""
    assert done[0] == (traj.ballistic_frames, 0)
    assert all(a[0] < b[0] and a[1] <= b[1] for a, b in zip(done, done[1:], strict=False))
    assert done[-1] == (len(traj), traj.substeps)


def test_the_flight_after_a_bounce_is_coasted_within_the_bound():
    """A rubber cube bounces at frame 4 and is still in the air when the clip ends: the MPM stops
    after take-off and the flight is computed in closed form (sim/coast.py). Against the explicit
    run: far fewer sub-steps and under a tenth of a pixel. A bound below the flight's predicted
    vibration (0.03-0.09 px here) keeps the explicit run."""
    gs = _shell_cube(2000, side=0.06, bottom=0.1)
    off = dict(allow_rigid=False, allow_bulk_cap=False, allow_stiffness_cap=False, allow_pressure=False)
    off["cells_across"] = 6
    done = {"explicit": [], "coast": [], "tight": []}  # what each run reported as it went
    runs = {
        name: simulate(
            gs,
            PhysicsSpec("rubber", E=1e6),
            GROUND,
            CAMERAS,
            n_frames=9,
            planner=PlannerConfig(**cfg),
            on_frame=_record(done[name]),
        )
        for name, cfg in {
            "explicit": {**off, "coast": False},
            "coast": {**off, "coast": True},
            "tight": {**off, "coast": True, "bound_px": 0.02},
        }.items()
    }
    explicit, coasted = runs["explicit"], runs["coast"]
    assert explicit.coasted_frames == 0 and runs["tight"].coasted_frames == 0
    assert runs["tight"].substeps == explicit.substeps
    assert coasted.coasted_frames >= 2 and coasted.ballistic_frames == explicit.ballistic_frames
    assert coasted.substeps < 0.6 * explicit.substeps
    d = (_pixels(coasted) - _pixels(explicit)).norm(dim=-1)  # [T, N]
    assert float(d.mean()) < 0.05 and float(d.max()) < 0.5
    # The flight's predicted error (its vibration's amplitude: the clip ends in the air) bounds it.
    assert float(d.max()) <= coasted.coast_predicted_px <= 0.5
    # Up to take-off the two runs are the same run.
    take_off = len(explicit) - coasted.coasted_frames
    np.testing.assert_array_equal(coasted.x[:take_off], explicit.x[:take_off])
    # Progress: each simulated frame of the explicit run; the flight as one step of the coasted run.
    for name, traj in runs.items():
        _check_progress(done[name], traj)
    assert [f for f, _ in done["explicit"]] == list(range(explicit.ballistic_frames, len(explicit) + 1))
    assert done["coast"][-1][0] - done["coast"][-2][0] == coasted.coasted_frames + 1


def test_a_landing_lump_with_its_bulk_capped_stays_within_the_dent_term():
    """A 10 cm plasticine cube (E = 1e6 Pa, nu = 0.45: c_p = 3.3 c_s) dropped 0.1 m dents and stays
    down. The planner caps its bulk modulus (c_p = 2 c_s) under the dent term (bulk_cap.dent_px,
    0.30 px); against the explicit run the Gaussians moved 0.08 px on average and 0.43 px at most,
    the volume ratio by 0.15 % (measured), for 40 % fewer sub-steps."""
    gs = _shell_cube(2000, side=0.1, bottom=0.1)
    physics = PhysicsSpec("plasticine", E=1e6, nu=0.45)
    base = dict(allow_rigid=False, allow_stiffness_cap=False, cells_across=8)
    explicit, capped = (
        simulate(gs, physics, GROUND, CAMERAS, n_frames=20, planner=PlannerConfig(**base, allow_bulk_cap=on))
        for on in (False, True)
    )
    plan = capped.plan
    assert explicit.plan.nu_used == pytest.approx(0.45) and plan.nu_used < 0.4
    assert plan.error_terms["bulk_cap_dent_px"] > 0 and plan.error_terms["bulk_cap_rebound_px"] == 0.0
    assert capped.substeps < 0.7 * explicit.substeps
    d = (_pixels(capped) - _pixels(explicit)).norm(dim=-1)  # [T, N]
    assert 0.01 < float(d.mean()) <= plan.predicted_error_px <= 0.5
    assert float(d.max()) < 1.0

    def volume(traj) -> np.ndarray:  # [T] sum(J V0) / sum(V0)
        v0 = traj.particles.volume.numpy()
        return (np.linalg.det(traj.F) * v0).sum(-1) / v0.sum()

    # The cap makes the lump more compressible: at most 1 % of its volume at any frame.
    assert float(np.abs(volume(capped) - volume(explicit)).max()) < 0.01


def test_the_stretch_scene_splits_the_particles_along_its_axis():
    """A stretch to twice the length gets two particles per lattice site along the pulled axis
    (planner.stretch_splits), a drop of the same object none; the mass is the same."""
    gs = _shell_cube(bottom=0.0)
    jelly = PhysicsSpec("jelly", E=5e4)
    drop = prepare_simulation(gs, jelly, "drop", CAMERAS, n_frames=3)
    pulled = prepare_simulation(gs, jelly, "stretch", CAMERAS, n_frames=3, scene_overrides={"axis": 1})
    assert len(pulled.sample) == 2 * len(drop.sample)
    assert float(pulled.sample.volume.sum()) == pytest.approx(float(drop.sample.volume.sum()), rel=1e-6)
    layers = np.unique(pulled.sample.x[:, 1].numpy().round(6))
    assert np.diff(layers).min() == pytest.approx(0.5 * drop.sample.spacing, rel=1e-3)


def test_a_stretch_past_what_the_material_survives_is_refused():
    """Fracture is not modelled: a stiff material pulled past its table's tensile limit stops with
    the limit, the strain asked and what to do; a stretch within it, a material without a limit
    and parameters given as they are (no table row) are planned."""
    gs = _shell_cube(bottom=0.0)
    with pytest.raises(
        ValueError,
        match=r"real ceramic fails in tension at about 0.002 strain.*"
        r"pulls parts of it to 1\.\d+.*Stretch it less",
    ):
        prepare_simulation(gs, PhysicsSpec("ceramic"), "stretch", CAMERAS, n_frames=3)
    with pytest.raises(ValueError, match="real metal fails in tension at about 0.5 strain"):
        prepare_simulation(gs, PhysicsSpec("metal"), "stretch", CAMERAS, n_frames=3)
    slight = prepare_simulation(
        gs, PhysicsSpec("ceramic"), "stretch", CAMERAS, n_frames=3, scene_overrides={"ratio": 1.001}
    )
    assert slight.plan.mode == "mpm"
    for physics in (PhysicsSpec("metal"), PhysicsSpec("jelly", E=5e4)):  # 30 %: metal draws that far
        prepare_simulation(gs, physics, "stretch", CAMERAS, n_frames=3, scene_overrides={"ratio": 1.3})
    prepare_simulation(gs, PhysicsSpec("ceramic").params(), "stretch", CAMERAS, n_frames=3)


def test_an_implicit_sub_step_is_predicted_as_several_passes():
    """The plan counts sub-steps; an implicit one costs at least IMPLICIT_PASSES_MIN passes over the
    particles (Newton's products and gradients), so its time is predicted that many times longer."""
    implicit = prepare_simulation(
        _shell_cube(),
        PhysicsSpec("jelly", E=5e4),
        "drop",
        CAMERAS,
        n_frames=6,
        solver=SolverConfig(integrator="implicit"),
    )
    explicit = replace(implicit, solver=SolverConfig())
    ratio = implicit.predicted_seconds(1e7) / explicit.predicted_seconds(1e7)
    assert implicit.predicted_seconds(1e7) > 0 and ratio == pytest.approx(IMPLICIT_PASSES_MIN)


def test_a_translucent_object_is_simulated_with_its_whole_body():
    """Gaussians drawn faint throughout (opacity 0.01-0.04, a jelly as the model draws it) carry mass
    at the planner's ``mass_opacity``: the particles fill the cube as they do when it is opaque;
    with the fixed threshold alone (relative_opacity 0) nothing is left to simulate."""
    opaque = _shell_cube(bottom=0.0)
    g = torch.Generator().manual_seed(3)
    faint = replace(opaque, opacities=0.01 + 0.03 * torch.rand(len(opaque.opacities), generator=g))
    jelly = PhysicsSpec("jelly", E=5e4)
    full = prepare_simulation(opaque, jelly, "drop", CAMERAS, n_frames=3)
    seen = prepare_simulation(faint, jelly, "drop", CAMERAS, n_frames=3)
    assert len(seen.sample) == len(full.sample)
    with pytest.raises(ValueError, match="opacity"):
        prepare_simulation(faint, jelly, "drop", CAMERAS, n_frames=3, planner={"relative_opacity": 0.0})


def test_the_plan_follows_the_pressure_integrator():
    """Under ``solver.integrator=pressure`` the explicit step follows the material's shear part:
    the plan predicts the sub-steps the split takes, and offers no bulk cap (the grid takes the
    volume term implicitly, so a cap would add its error and save no step). A soft rubber cube
    resting on the ground, which the explicit plan bulk-caps."""
    gs = _shell_cube(2000, side=0.1, bottom=0.0)
    physics = PhysicsSpec("rubber", E=2e5, nu=0.48)
    planner = PlannerConfig(
        allow_rigid=False, allow_stiffness_cap=False, allow_pressure=False, cells_across=8
    )
    explicit = prepare_simulation(gs, physics, GROUND, CAMERAS, 5, planner).plan
    uncapped = prepare_simulation(
        gs, physics, GROUND, CAMERAS, 5, replace(planner, allow_bulk_cap=False)
    ).plan
    split = SolverConfig(integrator="pressure")
    traj = simulate(gs, physics, GROUND, CAMERAS, n_frames=5, planner=planner, solver=split)
    plan = traj.plan
    assert explicit.nu_used < 0.45  # the explicit plan caps the bulk modulus
    assert (plan.E_used, plan.nu_used, plan.predicted_error_px) == (2e5, pytest.approx(0.48), 0.0)
    assert "pressure integrator" in plan.reason and "rebounds lower" not in plan.reason  # it rests
    # Dropped, the same cube lands elastically, and the plan says what the split does to its rebound.
    dropped = prepare_simulation(_shell_cube(2000, side=0.1), physics, GROUND, CAMERAS, 5, planner, split)
    assert "rebounds lower than explicit's" in dropped.plan.reason
    # sqrt((lam + 2 mu) / 2 mu) = 3.6 fewer sub-steps than the uncapped explicit step, as predicted ...
    assert plan.substeps_per_frame < uncapped.substeps_per_frame / 3.3
    # ... and as taken (the cube rests, so |v| adds little to the step's wave speed).
    assert traj.substeps == pytest.approx(4 * plan.substeps_per_frame, rel=0.1)


def test_a_rubber_drop_runs_with_the_pressure_split_the_planner_took():
    """The default planner takes the pressure split for a dropped rubber cube (nu = 0.48): the
    prepared solver runs it, the time is predicted at PRESSURE_STEP_COST explicit sub-steps each,
    and the solver takes the split's sub-steps, not explicit's (the solver sets its own step from
    the material it runs, so a count this low shows which one ran)."""
    gs, physics = _shell_cube(2000, side=0.1, bottom=0.05), PhysicsSpec("rubber", E=5e6, nu=0.48)
    planner = PlannerConfig(allow_rigid=False)  # 12 cells across: PRESSURE_MIN_CELLS
    split = prepare_simulation(gs, physics, GROUND, CAMERAS, 4, planner)
    explicit = prepare_simulation(gs, physics, GROUND, CAMERAS, 4, replace(planner, allow_pressure=False))
    assert (split.plan.integrator, split.solver.integrator) == ("pressure", "pressure")
    assert explicit.solver.integrator == "explicit"
    steps = explicit.plan.substeps_per_frame / split.plan.substeps_per_frame
    assert steps > 3.0
    seconds = explicit.predicted_seconds(1e7) / split.predicted_seconds(1e7)
    assert seconds == pytest.approx(steps / PRESSURE_STEP_COST)
    traj = run_prepared(split)
    assert traj.substeps <= 3 * split.plan.substeps_per_frame < 3 * explicit.plan.substeps_per_frame / 3


def test_the_plan_follows_the_implicit_integrator():
    """Under ``solver.integrator=implicit`` the sub-step is ``implicit_dt`` for a slow body, so the plan
    predicts those sub-steps, and caps neither E nor the bulk modulus (no cap would save a step). The
    soft rubber cube at rest, which the explicit plan caps."""
    gs = _shell_cube(2000, side=0.1, bottom=0.0)
    physics = PhysicsSpec("rubber", E=2e5, nu=0.48)
    planner = PlannerConfig(allow_rigid=False, allow_pressure=False, cells_across=6)
    explicit = prepare_simulation(gs, physics, GROUND, CAMERAS, 4, planner).plan
    implicit = SolverConfig(integrator="implicit", implicit_dt=0.01)
    traj = simulate(gs, physics, GROUND, CAMERAS, n_frames=4, planner=planner, solver=implicit)
    plan = traj.plan
    assert (explicit.E_used, explicit.nu_used) != (2e5, pytest.approx(0.48))  # the explicit plan caps
    assert (plan.E_used, plan.nu_used, plan.predicted_error_px) == (2e5, pytest.approx(0.48), 0.0)
    assert "implicit integrator" in plan.reason and "capped" not in plan.reason
    # A frame of 1 / 25 s in steps of at most 10 ms, fewer as the speed the plan allows for grows
    # (measured: 5, the float32 positions leaving a gap of a rounding error under the body), a
    # tenth of explicit's ...
    assert 4 <= plan.substeps_per_frame <= 6 and plan.substeps_per_frame < explicit.substeps_per_frame / 10
    # ... and what the solver took over the 3 simulated frames lies between the step at rest and the
    # prediction (measured: 14).
    assert 3 * 4 <= traj.substeps <= 3 * plan.substeps_per_frame


def test_the_grid_cut_short_of_a_tall_drop_follows_the_rebound():
    """A 5 cm jelly cube dropped 1 m with the cell cap at 24 cells (0.3 m): the planner keeps the
    body's cell and cuts the grid above the ground instead of coarsening it to 1.06 m. The grid
    rises with the rebound and comes back down, and the clip is the one on the whole height's grid
    at the same cell (``planner.max_cells=200``) to 0.1 mm."""
    gs = _shell_cube(800, side=0.05, bottom=1.0)
    physics = PhysicsSpec("jelly", E=2e4)
    planner = PlannerConfig(allow_rigid=False, cells_across=4, max_cells=24)
    cut = prepare_simulation(gs, physics, GROUND, CAMERAS, 30, planner)
    whole = prepare_simulation(gs, physics, GROUND, CAMERAS, 30, replace(planner, max_cells=200))
    assert cut.plan.dx == whole.plan.dx == pytest.approx(0.05 / 4, rel=1e-6)
    assert cut.plan.grid_hi[2] == pytest.approx(24 * cut.plan.dx) and whole.plan.grid_hi[2] > 1.0
    ref, followed = run_prepared(whole), run_prepared(cut)
    assert followed.grid_moves >= ref.grid_moves + 2  # up with the rebound, down again
    assert followed.face_contacts == ref.face_contacts == 0
    assert float(ref.x[:, :, 2].max(1)[15:].max()) > cut.plan.grid_hi[2]  # it rebounds past the cut
    assert float(np.abs(followed.x - ref.x).max()) < 1e-4  # m


def test_a_frame_whose_splash_meets_the_grids_faces_is_run_again_on_a_wider_grid(monkeypatch):
    """A 5 cm plasticine cube dropped 3 m (7.7 m/s) splats to twice its width. On a grid planned a
    cell narrower on each side than the planner's, the landing frame's splash meets the side faces:
    ``followed_grid`` reads its reach from the frame's start, when the body moves straight down.
    The frame is run again from its start on a grid that holds what it did, and the clip is the
    planned grid's to a fraction of a millimetre (measured 0.57 mm); without the retry the faces
    stopped mass in 4,060 node updates and the clip moved 9.7 mm."""
    gs = _shell_cube(800, side=0.05, bottom=3.0)
    planner = PlannerConfig(allow_rigid=False, cells_across=4)
    whole = prepare_simulation(gs, PhysicsSpec("plasticine", E=1e5), GROUND, CAMERAS, 40, planner)
    plan = whole.plan
    cell = np.array([plan.dx, plan.dx, 0.0])
    narrow = replace(whole, plan=replace(plan, grid_lo=plan.grid_lo + cell, grid_hi=plan.grid_hi - cell))
    ref, retried = run_prepared(whole), run_prepared(narrow)
    assert ref.face_contacts == retried.face_contacts == 0
    assert float(np.ptp(ref.x[-1, :, 0])) > 2 * 0.05 * 0.9  # the splat: about twice the cube's width
    assert float(np.abs(retried.x - ref.x).max()) < 1e-3  # m
    monkeypatch.setattr(mpm_run, "FACE_RETRIES", 0)
    stopped = run_prepared(narrow)
    assert stopped.face_contacts > 0
    assert float(np.abs(stopped.x - ref.x).max()) > 5e-3  # m


def test_a_flight_to_the_clips_end_may_leave_the_grid():
    """A rubber cube thrown sideways at 1 m/s over a frictionless floor bounces in frame 4 and is
    coasted in closed form from frame 6 to the clip's end, past the +x face of a grid cut 7 cm
    short. No frame is left to simulate, so no solver is built around it there (one was, and
    refused the particles outside its interior: a tall rubber drop under the pressure split
    crashed that way). The clip is the whole grid's."""
    gs = _shell_cube(2000, side=0.06, bottom=0.1)
    scene = (Scene(ground=GroundPlane(0.0, mode="slip")), np.array([1.0, 0.0, 0.0]))
    off = dict(allow_rigid=False, allow_bulk_cap=False, allow_stiffness_cap=False, cells_across=6)
    whole = prepare_simulation(gs, PhysicsSpec("rubber", E=1e6), scene, CAMERAS, 9, PlannerConfig(**off))
    plan = whole.plan
    cut = replace(whole, plan=replace(plan, grid_hi=plan.grid_hi - np.array([7 * plan.dx, 0.0, 0.0])))
    ref, short = run_prepared(whole), run_prepared(cut)
    assert ref.coasted_frames >= 2 and short.coasted_frames == ref.coasted_frames
    assert float(short.x[-1, :, 0].max()) > cut.plan.grid_hi[0]  # the flight ends past the face
    assert short.grid_moves == ref.grid_moves == 0 and short.face_contacts == 0
    np.testing.assert_array_equal(short.x, ref.x)


def test_the_grid_follows_a_body_that_leaves_the_planned_region():
    """A jelly cube slides across a frictionless floor at 1.5 m/s on a grid planned for a third of
    the way. The grid moves under it by whole cells, on the planned grid's own lattice, so the cube
    slides as it does on the whole planned grid; with ``planner.follow=False`` the faces stop it."""
    gs = _shell_cube(1000, side=0.1, bottom=0.0)
    scene = (Scene(ground=GroundPlane(0.0, mode="slip")), np.array([1.5, 0.0, 0.0]))
    physics = PhysicsSpec("jelly", E=2e4)
    planner = PlannerConfig(allow_rigid=False, cells_across=6)
    whole = prepare_simulation(gs, physics, scene, CAMERAS, 12, replace(planner, follow=False))
    plan = whole.plan
    cut = np.array([math.floor(0.35 / plan.dx) * plan.dx, 0.0, 0.0])  # whole cells: the same lattice
    held = replace(whole, plan=replace(plan, grid_hi=plan.grid_hi - cut))
    short = replace(held, planner=planner)
    ref, moved, stopped = (run_prepared(p) for p in (whole, short, held))
    assert ref.face_contacts == 0  # the planned grid holds the slide
    assert moved.face_contacts == 0 and moved.grid_moves >= 1
    assert float(np.abs(moved.x - ref.x).max()) < 1e-4  # m
    assert stopped.face_contacts > 0 and stopped.grid_moves == 0
    assert float(ref.x[-1, :, 0].max() - stopped.x[-1, :, 0].max()) > 0.1  # m short of where it slid


@pytest.mark.parametrize(("material", "mode"), [("metal", "rigid"), ("jelly", "mpm")])
def test_a_reordered_trajectory_moves_each_gaussian_as_before(material, mode):
    # What the renderer draws in depth order (render.frames.front_to_back) must be the same
    # Gaussians in the same places.
    traj = simulate(_shell_cube(n=600), PhysicsSpec(material), GROUND, CAMERAS, n_frames=4)
    assert traj.plan.mode == mode
    index = torch.randperm(len(traj.gaussians), generator=torch.Generator().manual_seed(2))
    reordered = traj.reordered(index)
    for t in (0, 3):
        a, b = traj.gaussians_at(t)[index], reordered.gaussians_at(t)
        for name in ("means", "quats", "scales", "opacities", "colors"):
            assert torch.equal(getattr(a, name), getattr(b, name)), (t, name)
    assert torch.equal(traj.means()[:, index], reordered.means())
    assert not torch.equal(traj.gaussians_at(3).means, traj.gaussians_at(0).means)  # it moved
