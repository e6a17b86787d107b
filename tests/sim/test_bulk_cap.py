"""Bulk cap: wave-speed algebra, the planner's choice under its bound, and a run against explicit MPM."""

from __future__ import annotations

import math

import pytest
import torch

from physgm.cameras import orbit_cameras
from physgm.sim.boundary import GroundPlane
from physgm.sim.bulk_cap import capped_material, choose_bulk_cap, nu_for_wave_ratio, wave_ratio
from physgm.sim.constitutive import MaterialParams
from physgm.sim.planner import PlannerConfig, choose_spacing, plan_simulation
from physgm.sim.scenes import Scene

CAMERAS = orbit_cameras(
    [30.0], [20.0], radius=1.0, fov_deg=40.0, width=256, height=256, target=(0.0, 0.0, 0.3)
)
RUBBER = MaterialParams("neo_hookean", E=5e6, nu=0.48, density=1100.0)


def _plan(material: MaterialParams, bottom: float = 0.5, **cfg):
    """Plan a 10 cm cube of ``material`` dropped from ``bottom`` m (1 cm particle spacing)."""
    g = torch.arange(-0.045, 0.05, 0.01)
    x = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + torch.tensor(
        [0, 0, bottom + 0.05]
    )
    vol = torch.full((len(x),), 1e-6)
    config = PlannerConfig(**cfg)
    dx, spacing = choose_spacing(0.1, config)
    scene = Scene(ground=GroundPlane(0.0, friction=0.3))
    return plan_simulation(
        x, vol, torch.zeros_like(x), "rubber", material, scene, CAMERAS, 50, 0.04, dx, spacing, config
    )


def test_wave_ratio_round_trip_and_shear_kept():
    assert wave_ratio(1 / 3) == pytest.approx(2.0)
    assert wave_ratio(0.48) == pytest.approx(math.sqrt(2 * 0.52 / 0.04))
    for r in (1.5, 2.0, 3.0, 5.0):
        assert wave_ratio(nu_for_wave_ratio(r)) == pytest.approx(r)
    capped = capped_material(RUBBER, 2.0)
    assert capped.mu == pytest.approx(RUBBER.mu) and capped.nu == pytest.approx(1 / 3)
    # The step follows c_p, now twice the (unchanged) shear wave speed.
    assert capped.wave_speed() == pytest.approx(2.0 * math.sqrt(RUBBER.mu / RUBBER.density))
    assert RUBBER.wave_speed() / capped.wave_speed() == pytest.approx(wave_ratio(0.48) / 2.0)
    assert capped_material(RUBBER.with_elasticity(nu=0.3), 2.0).nu == 0.3  # already below: unchanged


def test_choose_bulk_cap_stays_within_budget_and_is_monotone():
    def deformation_px(E: float) -> float:  # sag + impact of a 10 cm rubber block at 2 m/s, 400 px/m
        return (1100 * 9.81 * 0.01 / E + 2.0 * 0.1 / math.sqrt(E / 1100)) * 400

    picks = [choose_bulk_cap(RUBBER, deformation_px, 40.0, True, b, 2.0) for b in (0.05, 0.1, 0.2, 5.0)]
    ratios = [p.ratio for p in picks]
    assert all(a > b for a, b in zip(ratios, ratios[1:], strict=False))  # a larger budget caps harder
    assert ratios[-1] == 2.0  # the floor
    for pick, budget in zip(picks[:-1], (0.05, 0.1, 0.2), strict=True):
        assert pick.predicted_px == pytest.approx(budget, rel=1e-6)  # spends the budget exactly
        assert pick.rebound_px > 0 and pick.material.mu == pytest.approx(RUBBER.mu)
    # No budget at all: no cap.
    assert choose_bulk_cap(RUBBER, deformation_px, 40.0, True, 0.0, 2.0) is None
    sand = MaterialParams("drucker_prager", E=3.5e5, nu=0.45, density=1600.0, friction_angle=30.0)
    assert choose_bulk_cap(sand, deformation_px, 40.0, False, 5.0, 2.0) is None  # pressure-sensitive


def test_planner_takes_bulk_cap_only_under_its_bound():
    plan = _plan(RUBBER)
    assert plan.mode == "mpm" and plan.nu_used < RUBBER.nu
    mu_used = plan.E_used / (2 * (1 + plan.nu_used))
    assert mu_used == pytest.approx(RUBBER.mu, rel=1e-9)
    # An elastic impact: the stiffness cap is off, so the bulk cap may use the whole bound.
    assert 0 < plan.predicted_error_px <= PlannerConfig().bound_px + 1e-9
    assert plan.error_terms["bulk_cap_px"] == plan.predicted_error_px
    assert plan.predicted_cost < plan.alternatives["mpm"] / 1.25
    # A tighter bound keeps more bulk stiffness and still meets it.
    strict = _plan(RUBBER, bound_px=0.1)
    assert plan.nu_used <= strict.nu_used <= RUBBER.nu and strict.predicted_error_px <= 0.1 + 1e-9
    # Off, or a material far from incompressible (c_p < 2 c_s): nothing changes.
    assert _plan(RUBBER, allow_bulk_cap=False).nu_used == RUBBER.nu
    foam_like = MaterialParams("neo_hookean", E=5e6, nu=0.2, density=1100.0)
    assert _plan(foam_like).nu_used == 0.2 and _plan(foam_like).error_terms["bulk_cap_px"] == 0.0
    # force_caps (benchmarks) takes the floor ratio whatever it costs.
    forced = _plan(RUBBER, bound_px=0.1, force_caps=True, allow_stiffness_cap=False)
    assert forced.nu_used == pytest.approx(nu_for_wave_ratio(2.0))
