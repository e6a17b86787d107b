"""Planner: deformation estimates, mode choice, stiffness cap, grid fitting, pixel scale."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch

from physgm.cameras import orbit_cameras
from physgm.sim.coast import ballistic_frames
from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm.boundary import GroundPlane, VelocityBox
from physgm.sim.mpm.pressure import PRESSURE_STEP_COST
from physgm.sim.mpm.scene import Scene
from physgm.sim.planner import (
    PlannerConfig,
    choose_spacing,
    deformation_estimate,
    pixels_per_metre,
    plan_simulation,
    reachable_region,
    stiffness_cap,
    stretch_splits,
)

G = 9.81
CAMERAS = orbit_cameras(
    [30.0], [20.0], radius=1.0, fov_deg=40.0, width=256, height=256, target=(0.0, 0.0, 0.3)
)


def _cube(side: float = 0.1, bottom: float = 0.5, spacing: float = 0.01) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.arange(-side / 2 + spacing / 2, side / 2, spacing)
    x = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + torch.tensor(
        [0.0, 0.0, bottom + side / 2]
    )
    return x, torch.full((len(x),), spacing**3)


def _plan(
    material: MaterialParams, name: str = "custom", scene: Scene | None = None, bottom: float = 0.5, **cfg
):
    x, vol = _cube(bottom=bottom)
    scene = scene or Scene(ground=GroundPlane(0.0, friction=0.3))
    config = PlannerConfig(**cfg)
    dx, spacing = choose_spacing(0.1, config)
    return plan_simulation(
        x, vol, torch.zeros_like(x), name, material, scene, CAMERAS, 50, 0.04, dx, spacing, config
    )


STEEL = MaterialParams("von_mises", E=2e11, nu=0.3, density=7850.0, yield_stress=2.5e8)
JELLY = MaterialParams("fixed_corotated", E=1e5, nu=0.3, density=1000.0)
GROUND = Scene(ground=GroundPlane(0.0, friction=0.3))
SAND = MaterialParams("drucker_prager", E=3.5e7, nu=0.3, density=1600.0, friction_angle=30.0)


def test_deformation_estimate_formulas():
    d = deformation_estimate(E=1e6, density=1000.0, size=0.2, impact_speed=2.0)
    assert d.sag == pytest.approx(1000 * G * 0.04 / 1e6)
    assert d.impact == pytest.approx(2.0 * 0.2 / math.sqrt(1e6 / 1000))
    assert d.plastic == 0.0 and not d.flows
    # Past yield: the kinetic energy goes into a dent rho L v^2 / (2 sigma_y).
    d = deformation_estimate(E=7e10, density=2700.0, size=0.1, impact_speed=5.0, yield_stress=3e7)
    assert d.plastic == pytest.approx(2700 * 0.1 * 25 / (2 * 3e7))
    # Weaker than its own weight: flows.
    assert deformation_estimate(E=1e6, density=1500.0, size=0.1, impact_speed=0.0, yield_stress=100.0).flows


def test_pixels_per_metre_is_focal_over_depth():
    cams = orbit_cameras([0.0], [0.0], radius=2.0, fov_deg=60.0, width=200, height=100)
    focal = 100 / math.tan(math.radians(30))
    assert pixels_per_metre(cams, torch.zeros(1, 3)) == pytest.approx(focal / 2.0, rel=1e-5)
    # The closest point sets the scale.
    pts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    assert pixels_per_metre(cams, pts) == pytest.approx(focal / 1.0, rel=1e-5)


def test_steel_drop_goes_rigid_jelly_goes_mpm():
    steel = _plan(STEEL, "metal")
    assert steel.mode == "rigid"
    assert steel.predicted_error_px < 0.5
    assert steel.E_used == STEEL.E
    jelly = _plan(JELLY, "jelly")
    assert jelly.mode == "mpm" and jelly.E_used == JELLY.E  # its deformation is the point: no cap
    assert jelly.error_terms["impact_px"] > 0.5
    assert "deforms" in jelly.reason


@pytest.mark.parametrize("name", ["sand", "snow"])
def test_granular_never_rigid_even_when_stiff(name):
    stiff = MaterialParams("drucker_prager", E=1e12, nu=0.3, density=1600.0, friction_angle=35.0)
    plan = _plan(stiff, name, bound_px=50.0)
    assert plan.mode == "mpm"
    # By name alone as well (snow may use another model in the table).
    assert _plan(MaterialParams("fixed_corotated", E=1e12, nu=0.3, density=400.0), name).mode == "mpm"


@pytest.mark.parametrize("name", ["sand", "snow"])
def test_a_flowing_material_keeps_its_stiffness(name):
    # A granular cube set on the ground collapses: how far it runs out follows E, so no cap. Before
    # this, the planner capped sand (3.5e5 -> 1.9e5 Pa) predicting 0.25 px, and the collapse ended
    # 1.31 px from the full-stiffness run (docs/measurements_sim.md section 32).
    granular = MaterialParams("drucker_prager", E=3.5e5, nu=0.3, density=1600.0, friction_angle=35.0)
    resting = _plan(granular, name, bottom=0.0)
    assert resting.mode == "mpm" and resting.E_used == granular.E and resting.nu_used == granular.nu
    assert resting.predicted_error_px == 0.0 and "a flow" in resting.reason
    # The same stiffness in a solid that springs back is capped at rest (its estimate holds there).
    solid = MaterialParams("fixed_corotated", E=3.5e5, nu=0.3, density=1600.0)
    assert _plan(solid, "custom", bottom=0.0, allow_rigid=False, allow_bulk_cap=False).E_used < solid.E
    dropped = _plan(granular, name)
    assert dropped.E_used == granular.E and "a flow" in dropped.reason


def test_prescribed_motion_is_never_rigid():
    grip = VelocityBox(lo=(-0.1, -0.1, 0.58), hi=(0.1, 0.1, 0.7), velocity=(0.0, 0.0, 0.1))
    plan = _plan(STEEL, "metal", scene=Scene(ground=GroundPlane(), boxes=(grip,)))
    assert plan.mode == "mpm" and "prescribes" in plan.reason


def test_stiffness_cap_meets_bound_and_is_monotone():
    E, rho, size, v = 5e9, 1200.0, 0.1, 3.0
    bounds = [1e-5, 1e-4, 1e-3, 1e-2]
    caps = [stiffness_cap(E, rho, size, v, b) for b in bounds]
    assert all(a > b for a, b in zip(caps, caps[1:], strict=False))
    for cap, b in zip(caps, bounds, strict=True):
        extra = deformation_estimate(cap, rho, size, v)
        base = deformation_estimate(E, rho, size, v)
        assert (extra.sag + extra.impact) - (base.sag + base.impact) == pytest.approx(b, rel=1e-6)
    assert stiffness_cap(E, rho, size, v, 0.0) == pytest.approx(E)


def test_plan_prices_the_stiffness_cap_of_a_visible_dent():
    # Soft aluminium dropped from 2 m: the dent is visible (MPM). A lower E moves the dent by
    # STIFFNESS_DENT_GAIN x the relative change of c_p x the object's size (measured on plasticine
    # drops), so within the default 0.5 px nothing worth 1.25x is left: E stays.
    alu = MaterialParams("von_mises", E=7e10, nu=0.33, density=2700.0, yield_stress=1e6)
    plan = _plan(alu, "metal", bottom=2.0)
    assert plan.mode == "mpm" and plan.error_terms["plastic_px"] > 0.5
    assert plan.E_used == alu.E and plan.predicted_error_px == 0.0
    # Within 5 px (still below the rigid path's 5.2) the cap spends its share on the dent term.
    loose = _plan(alu, "metal", bottom=2.0, bound_px=5.0)
    share = PlannerConfig().cap_budget * 5.0
    assert loose.mode == "mpm" and loose.E_used < alu.E
    assert loose.error_terms["stiffness_cap_dent_px"] == pytest.approx(share, rel=1e-6)
    assert loose.predicted_error_px == pytest.approx(share, rel=1e-6)
    assert loose.predicted_cost < plan.alternatives["mpm"] / 1.25
    # A stricter bound keeps more stiffness.
    strict = _plan(alu, "metal", bottom=2.0, bound_px=3.0)
    assert loose.E_used < strict.E_used <= alu.E
    assert _plan(alu, "metal", bottom=2.0, bound_px=5.0, allow_stiffness_cap=False).E_used == alu.E


def test_grid_fits_reachable_region_and_is_small():
    plan = _plan(JELLY, "jelly")
    x, _ = _cube()
    assert np.all(plan.grid_lo <= x.min(0).values.numpy()) and np.all(plan.grid_hi >= x.max(0).values.numpy())
    assert plan.grid_lo[2] <= 0.0  # reaches the ground
    # Top: the centre (0.55 m) plus the farthest particle's distance (tumbling).
    assert plan.grid_hi[2] == pytest.approx(0.55 + 0.045 * math.sqrt(3), abs=1e-6)
    cells = np.ceil((plan.grid_hi - plan.grid_lo) / plan.dx)
    assert cells.max() <= PlannerConfig().max_cells
    assert cells.prod() < 200**3 / 50
    # cells_across cells over the object (unless the cell cap coarsened it).
    cfg = PlannerConfig()
    expected = min(cfg.cells_across, cfg.max_cells * 0.1 / (plan.grid_hi - plan.grid_lo).max())
    assert 0.1 / plan.dx == pytest.approx(expected, rel=1e-6)
    # The naive baseline: a fixed 1 m cube at the same cell size holds far more nodes.
    naive = _plan(JELLY, "jelly", fit_grid=False)
    naive_cells = np.ceil((naive.grid_hi - naive.grid_lo) / naive.dx)
    assert naive.grid_lo[2] == 0.0 and naive_cells.prod() > 20 * cells.prod()


def test_a_drop_taller_than_the_cell_cap_keeps_the_cell_its_body_asks_for():
    """A 0.1 m cube 3 m up: 376 cells of the body's 8.3 mm would pass ``max_cells`` (96). The fall
    before the first contact is closed form, so the grid holds only the 96 cells above the ground,
    which hold the body from where the simulation takes over, and follows a rebound; without the
    closed-form fall or without following, the grid coarsens to fit the height, as a bound scene's does."""
    cfg = PlannerConfig()
    plan = _plan(JELLY, "jelly", bottom=3.0)
    assert plan.dx == pytest.approx(0.1 / cfg.cells_across, rel=1e-9)
    assert plan.cells_across == pytest.approx(cfg.cells_across, rel=1e-9)
    assert plan.grid_lo[2] <= 0.0 and (plan.grid_hi[2] - plan.grid_lo[2]) / plan.dx == pytest.approx(
        cfg.max_cells
    )
    # Where the simulation takes over (a frame before the lowest point is 3 cells up), the body fits.
    x, _ = _cube(bottom=3.0)
    k0 = ballistic_frames(
        x.numpy(), np.zeros((len(x), 3)), Scene(ground=GroundPlane(0.0)), 0.04, 50, 3 * plan.dx
    )
    t = (k0 - 1) * 0.04
    assert k0 > 1 and float(x[:, 2].max()) - 0.5 * G * t * t < plan.grid_hi[2]
    whole_height = 3.05 + 0.045 * math.sqrt(3)  # the top as the region has it: centre + radius
    for kw in ({"ballistic": False}, {"follow": False}):
        coarse = _plan(JELLY, "jelly", bottom=3.0, **kw)
        assert coarse.dx == pytest.approx(whole_height / cfg.max_cells, rel=1e-6)
        assert coarse.grid_hi[2] == pytest.approx(whole_height, abs=1e-6)
        assert f"coarser than the {plan.dx:.3g} m the object asks for" in coarse.reason
        assert coarse.cells_across == pytest.approx(0.1 / coarse.dx, rel=1e-6)  # 3.1 across the 0.1 m cube
    assert "coarser" not in plan.reason
    boxed = Scene(
        ground=GroundPlane(0.0), boxes=(VelocityBox((-1.0, -1.0, 5.0), (1.0, 1.0, 5.1), (0.0, 0.0, 0.0)),)
    )
    assert _plan(JELLY, "jelly", scene=boxed, bottom=3.0).dx > 2 * plan.dx
    # A short drop is planned whole, as before.
    assert _plan(JELLY, "jelly").grid_hi[2] == pytest.approx(0.55 + 0.045 * math.sqrt(3), abs=1e-6)


def test_reachable_region_includes_velocity_drift_and_grips():
    x, _ = _cube(bottom=0.0)
    v0 = torch.zeros_like(x)
    v0[:, 0] = 1.0
    lo, hi = reachable_region(x, v0, 0.5, np.array([0, 0, -G]), 0.0, spread=0.0)
    radius = float((x - x.mean(0)).norm(dim=-1).max())  # tumbling reach about the centre
    assert hi[0] == pytest.approx(float(x[:, 0].mean()) + radius + 0.5, abs=1e-6)
    assert lo[0] == pytest.approx(float(x[:, 0].mean()) - radius - 0.5, abs=1e-6)
    # A spread wider than the tumbling reach sets the footprint instead.
    lo, hi = reachable_region(x, torch.zeros_like(x), 0.5, np.array([0, 0, -G]), 0.0, spread=0.3)
    assert hi[1] == pytest.approx(float(x[:, 1].max()) + 0.3, abs=1e-6)
    assert lo[2] == pytest.approx(0.0, abs=1e-6)
    # On the ground with friction mu the slide stops after v^2 / (2 mu g).
    lo, hi = reachable_region(x, v0, 0.5, np.array([0, 0, -G]), 0.0, spread=0.0, friction=0.5)
    t_air = math.sqrt(2 * float(x[:, 2].min()) / G)  # the lowest particle is 5 mm up: it lands first
    assert hi[0] == pytest.approx(float(x[:, 0].mean()) + radius + t_air + 1.0 / (2 * 0.5 * G), abs=1e-6)
    grip = (np.array([0.0, 0.0, 0.0]), np.array([0.1, 0.1, 0.1]), np.array([0.0, 0.0, 0.2]), 1.0)
    lo, hi = reachable_region(x, torch.zeros_like(x), 1.0, np.array([0, 0, -G]), 0.0, 0.0, [grip])
    assert hi[2] == pytest.approx(0.3)


def test_cap_spends_its_budget_and_keeps_nu():
    # Stiff rubber (nu = 0.48 makes it costly) resting on the ground (rigid off: it would not
    # deform visibly), so capped. (The bulk cap, off here, has its own tests; the caps of the explicit
    # step, so the pressure split is off too.)
    rubber = MaterialParams("neo_hookean", E=5e7, nu=0.48, density=1100.0)
    explicit = functools.partial(_plan, rubber, "rubber", allow_pressure=False)
    plan = explicit(bottom=0.0, allow_bulk_cap=False, allow_rigid=False)
    assert plan.mode == "mpm" and plan.E_used < rubber.E
    # The cap spends only cap_budget of the bound; the extra deformation equals that share.
    assert plan.predicted_error_px == pytest.approx(PlannerConfig().cap_budget * 0.5, rel=1e-6)
    assert plan.predicted_cost < plan.alternatives["mpm"] / 1.25
    off = explicit(bottom=0.0, allow_stiffness_cap=False, allow_bulk_cap=False, allow_rigid=False)
    assert off.E_used == rubber.E
    # Its top pulled up by a grip: no cap, bulk or E (their models failed on the stretch scene).
    grip = VelocityBox(lo=(-0.1, -0.1, 0.08), hi=(0.1, 0.1, 0.2), velocity=(0.0, 0.0, 0.5))
    pulled = explicit(scene=Scene(ground=GroundPlane(), boxes=(grip,)), bottom=0.0)
    assert (pulled.E_used, pulled.nu_used, pulled.predicted_error_px) == (rubber.E, rubber.nu, 0.0)
    assert "moving boxes drive the body" in pulled.reason
    # Dropped from 1 m it bounces: the rebound depends on E, so no cap (and nothing promised).
    dropped = explicit(bottom=1.0, allow_bulk_cap=False)
    assert dropped.mode == "mpm" and dropped.E_used == rubber.E and dropped.predicted_error_px == 0.0
    assert "not capped" in dropped.reason
    fast = explicit(bottom=1.0, cap_elastic_impacts=True, allow_bulk_cap=False)  # the opt-in
    assert fast.E_used < rubber.E and fast.predicted_cost < dropped.predicted_cost / 1.25
    # Yield is checked with the impact stress rho c_p v (P-wave speed, the larger one).
    c_p = rubber.wave_speed()
    d = deformation_estimate(
        5e6, 1100.0, 0.1, 2.0, yield_stress=1100 * c_p * 2.0 * 0.99, wave_factor=c_p**2 * 1100 / 5e6
    )
    assert d.plastic > 0


RUBBER = MaterialParams("neo_hookean", E=5e6, nu=0.48, density=1100.0)


def test_the_planner_takes_the_pressure_split_where_its_fewer_sub_steps_pay():
    """A dropped rubber cube (nu = 0.48, 12 cells across) runs with the pressure split: its step
    follows the shear wave, about 3.5x fewer sub-steps than explicit's, which pays for the split's
    solve (PRESSURE_STEP_COST each) by more than min_cap_gain. At nu = 0.3 the split would save 1.4x,
    not enough; nor is it taken for a slab under PRESSURE_MIN_CELLS cells thick, when switched off,
    under another integrator, or where it cannot run."""
    config = PlannerConfig()
    dx, spacing = choose_spacing(0.1, config)
    cube = _cube(spacing=spacing)  # the planner's own lattice: 24 particles, 12 cells across

    def plan(material, name="rubber", scene=GROUND, x_vol=cube, integrator="explicit", **cfg):
        x, vol = x_vol
        cfg = PlannerConfig(**cfg)
        args = (x, vol, torch.zeros_like(x), name, material, scene, CAMERAS, 50, 0.04, dx, spacing, cfg)
        return plan_simulation(*args, integrator)

    split = plan(RUBBER)
    assert (split.mode, split.integrator) == ("mpm", "pressure")
    assert (split.E_used, split.nu_used, split.predicted_error_px) == (RUBBER.E, RUBBER.nu, 0.0)
    assert "pressure split" in split.reason and "rebounds lower" in split.reason
    gain = split.alternatives["mpm"] / split.alternatives["mpm_pressure"]
    assert gain >= config.min_cap_gain * PRESSURE_STEP_COST and gain > 3.0
    assert split.predicted_cost == split.alternatives["mpm_pressure"]

    off = plan(RUBBER, allow_pressure=False)
    assert off.integrator == "explicit" and off.predicted_cost == split.alternatives["mpm"]
    assert "pressure" not in off.reason
    lower = plan(RUBBER.with_elasticity(E=RUBBER.E, nu=0.3))
    saving = lower.alternatives["mpm"] / lower.alternatives["mpm_pressure"]
    assert lower.integrator == "explicit" and 1.2 < saving < config.min_cap_gain * PRESSURE_STEP_COST
    assert plan(JELLY.with_elasticity(E=1e5, nu=0.48), "jelly").integrator == "pressure"  # fixed-corotated
    assert plan(STEEL, "metal", allow_rigid=False).integrator == "explicit"  # von Mises: no split
    # The same rubber as a slab 9 cells thick (the cube's top quarter cut off), flat or turned 30
    # degrees about x: explicit.
    x, vol = cube
    keep = x[:, 2] < x[:, 2].min() + 9 * dx - spacing / 2
    slab = x[keep]
    turn = torch.tensor(
        [[1.0, 0.0, 0.0], [0.0, math.cos(0.52), -math.sin(0.52)], [0.0, math.sin(0.52), math.cos(0.52)]]
    )
    for body in (slab, (slab - slab.mean(0)) @ turn.T.to(slab) + slab.mean(0)):
        thin = plan(RUBBER, x_vol=(body, vol[keep]))
        assert thin.integrator == "explicit" and "mpm_pressure" not in thin.alternatives
    for integrator in ("implicit", "pressure"):  # the solver's own integrator is kept
        assert plan(RUBBER, integrator=integrator).integrator == integrator
    grip = VelocityBox(lo=(-0.1, -0.1, 0.58), hi=(0.1, 0.1, 0.7), velocity=(0.0, 0.0, 0.1))
    gripped = plan(RUBBER, scene=Scene(ground=GroundPlane(0.0, friction=0.3), boxes=(grip,)))
    assert gripped.integrator == "explicit" and "mpm_pressure" not in gripped.alternatives


def test_yaml_config_matches_dataclass_defaults():
    import dataclasses
    from pathlib import Path

    import yaml

    path = Path(__file__).resolve().parents[2] / "conf" / "sim" / "planner" / "default.yaml"
    values = yaml.safe_load(path.read_text())
    assert set(values) == {f.name for f in dataclasses.fields(PlannerConfig)}
    assert PlannerConfig(**values) == PlannerConfig()
    with pytest.raises(ValueError, match="bound_px"):
        PlannerConfig(bound_px=0.0)
    with pytest.raises(ValueError, match="rest_frames=0"):
        PlannerConfig(rest_frames=0)
    with pytest.raises(ValueError, match="rest_budget_px"):
        PlannerConfig(rest_budget_px=-0.1)


def test_stiff_object_thrown_at_a_still_wall_is_rigid_and_a_soft_one_is_not():
    x, vol = _cube(bottom=0.0)
    wall = VelocityBox(lo=(0.1, -1.0, -1.0), hi=(0.15, 1.0, 1.0))  # 5 cm ahead along +x
    scene = Scene(ground=GroundPlane(0.0, friction=0.3), boxes=(wall,))
    v0 = torch.zeros_like(x)
    v0[:, 0] = 2.0
    config = PlannerConfig()
    dx, spacing = choose_spacing(0.1, config)

    def plan(material, name):
        return plan_simulation(x, vol, v0, name, material, scene, CAMERAS, 50, 0.04, dx, spacing, config)

    steel = plan(STEEL, "metal")
    assert steel.mode == "rigid"
    jelly = plan(JELLY, "jelly")
    # The throw is the load: a jelly hitting the wall at 2 m/s squashes visibly, and is not capped.
    assert jelly.mode == "mpm" and jelly.E_used == JELLY.E and jelly.error_terms["impact_px"] > 0.5


def test_stretch_splits_keep_stretched_particles_within_the_spacing_bound():
    cfg = PlannerConfig()  # particles at dx / 2, at most 0.67 cells apart when stretched
    assert stretch_splits(1.3, 0.5, 1.0, cfg) == 1
    assert stretch_splits(2.3, 0.5, 1.0, cfg) == 2
    assert stretch_splits(3.4, 0.5, 1.0, cfg) == 3
    assert stretch_splits(3.4, 0.5, 1.0, PlannerConfig(max_stretched_spacing=1.0)) == 2
    assert stretch_splits(50.0, 0.5, 1.0, cfg) == 4  # capped
    with pytest.raises(ValueError, match="max_stretched_spacing"):
        PlannerConfig(max_stretched_spacing=0.0)
