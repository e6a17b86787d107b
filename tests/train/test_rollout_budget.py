"""Bounded rollouts: over-budget plans fall back to the planner's cheaper settings, or are skipped or cut,
with the reason logged; the solver's deadline really stops an MPM run; skipped candidates never pair."""

from __future__ import annotations

import logging
import time
from types import SimpleNamespace

import pytest
import torch

import physgm.sim.gaussian_trajectory as gt
from physgm.gaussians import Gaussians
from physgm.physics.materials import PhysicsSpec
from physgm.sim.mpm_run import SimulationBudgetExceeded
from physgm.train.pairs import Candidate, PairCache, SceneRecord, select_pair
from physgm.train.rollout_budget import THROUGHPUT, BudgetConfig, bounded_simulate


def fake_prepared(cost: float, error: float, n_frames: int = 11):
    plan = SimpleNamespace(mode="mpm", n_frames=n_frames, predicted_cost=cost, predicted_error_px=error)
    prepared = SimpleNamespace(plan=plan, ballistic_frames=1, solver=SimpleNamespace(integrator="explicit"))
    # the real prediction, on the stand-in's plan
    prepared.predicted_seconds = lambda throughput: gt.PreparedSimulation.predicted_seconds(
        prepared, throughput
    )
    return prepared


class FakeSim:
    """prepare_simulation / run_prepared stand-ins: a plan's cost and error per planner setting."""

    def __init__(self, plans: dict, slow: bool = False):
        self.plans, self.slow, self.ran = plans, slow, []

    def prepare(self, gaussians, physics, scene, camera, n_frames, planner, solver, overrides):
        key = (planner.get("cap_elastic_impacts", False), planner.get("bound_px", 0.5))
        return fake_prepared(*self.plans[key])

    def run(self, prepared, device="cpu", deadline=None):
        self.ran.append(prepared.plan.predicted_cost)
        if self.slow:  # the prediction was too optimistic: the solver's deadline cuts it
            raise SimulationBudgetExceeded(3, prepared.plan.n_frames)
        return SimpleNamespace(plan=prepared.plan, substeps=0, seconds=0.0, plan_seconds=0.0)


def run_bounded(monkeypatch, sim: FakeSim, **budget):
    monkeypatch.setattr(gt, "prepare_simulation", sim.prepare)
    monkeypatch.setattr(gt, "run_prepared", sim.run)
    THROUGHPUT.clear()
    cfg = BudgetConfig(**{"max_seconds": 30.0, "throughput": 1e6, **budget})
    physics = PhysicsSpec("rubber", E=3e7, nu=0.45)
    return bounded_simulate(None, physics, "drop", None, 11, {"bound_px": 0.5}, None, {}, "cpu", cfg)


def test_over_budget_plan_falls_back_to_the_cheaper_planner_setting_with_its_error(monkeypatch):
    # 1e8 particle-substeps at 1e6 /s: 100 s as planned; capped after the impact: 20 s at 0.8 px.
    sim = FakeSim({(False, 0.5): (1e8, 0.0), (True, 0.5): (2e7, 0.8), (True, 2.0): (5e6, 3.0)})
    run = run_bounded(monkeypatch, sim)
    assert run.skipped is None and run.fallback == 0 and sim.ran == [2e7]
    assert run.planner == {"bound_px": 0.5, "cap_elastic_impacts": True}
    assert run.predicted_seconds == pytest.approx(20.0) and run.predicted_error_px == 0.8


def test_plan_over_budget_with_every_setting_is_skipped_and_the_reason_logged(monkeypatch, caplog):
    sim = FakeSim({(False, 0.5): (1e9, 0.0), (True, 0.5): (5e8, 0.5), (True, 2.0): (1e8, 2.0)})
    with caplog.at_level(logging.WARNING, logger="physgm.train.rollout"):
        run = run_bounded(monkeypatch, sim)
    assert run.trajectory is None and sim.ran == []  # nothing simulated
    assert run.skipped.startswith("skipped: predicted over the 30 s budget")
    assert (
        "as planned: 1000 s" in run.skipped and "cap_elastic_impacts=True, bound_px=2.0: 100 s" in run.skipped
    )
    assert "rubber E=3e+07 Pa skipped" in caplog.text
    # A cheaper setting whose predicted error is over max_error_px is never used, even when it would fit.
    sim = FakeSim({(False, 0.5): (1e9, 0.0), (True, 0.5): (1e6, 9.0), (True, 2.0): (1e6, 20.0)})
    run = run_bounded(monkeypatch, sim)
    assert run.trajectory is None and sim.ran == [] and "skipped" in run.skipped


def test_a_run_past_its_deadline_is_cut_and_logged(monkeypatch, caplog):
    sim = FakeSim({(False, 0.5): (1e6, 0.0)}, slow=True)
    with caplog.at_level(logging.WARNING, logger="physgm.train.rollout"):
        run = run_bounded(monkeypatch, sim)
    assert run.trajectory is None and run.skipped.startswith("cut: cut at frame 3 of 11")
    assert "cut" in caplog.text


def test_the_solver_deadline_stops_a_real_mpm_run_between_frames():
    gen = torch.Generator().manual_seed(0)
    n = 300
    g = Gaussians(
        torch.rand(n, 3, generator=gen) * 0.1 + torch.tensor([0.0, 0.0, 0.02]),
        torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        torch.full((n, 3), 0.01),
        torch.full((n,), 0.9),
        torch.rand(n, 3, generator=gen),
    )
    from physgm.cameras import orbit_cameras

    cams = orbit_cameras([0.0], [10.0], 1.0, 40.0, 32, 32)
    physics = PhysicsSpec("jelly", E=1e4, nu=0.3)
    prepared = gt.prepare_simulation(g, physics, "drop", cams, 6, {"cells_across": 6, "ballistic": False})
    assert prepared.plan.mode == "mpm" and prepared.ballistic_frames == 1
    with pytest.raises(SimulationBudgetExceeded, match="cut at frame 1 of 6"):
        gt.run_prepared(prepared, "cpu", deadline=time.perf_counter())
    traj = gt.run_prepared(prepared, "cpu", deadline=time.perf_counter() + 600)  # ample: runs to the end
    assert traj.x.shape[0] == 6


def test_skipped_candidates_never_pair_and_round_trip_through_the_cache(tmp_path):
    cands = [
        Candidate(0, "rubber", 6.0, 0.4, 0.05),
        Candidate(0, "rubber", 7.5, 0.4, None, skipped="skipped: predicted over the 30 s budget"),
        Candidate(0, "rubber", 5.0, 0.4, 0.20, source="wide", fallback=0, predicted_error_px=0.8),
    ]
    assert select_pair(cands, 0.002) == (0, 2, "")  # the skipped one is neither winner nor loser
    assert select_pair(cands[:2], 0.002)[:2] == (None, None)  # one finished candidate: no pair
    record = SceneRecord("s0", 0, 0, "settings", "policy", cands, 0, 2)
    cache = PairCache(tmp_path)
    cache.write(record)
    assert cache.read(0, "s0", "settings", "policy") == record
