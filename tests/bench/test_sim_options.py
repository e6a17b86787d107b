"""``bench sim --only options``: the CFL rows against the explicit reference."""

import pytest

from physgm.bench import sim_options
from physgm.bench.drop_scene import DropBench
from physgm.sim.mpm.stepping import SimulationDiverged

# 12 frames of the 15 cm cube: 8 in closed-form free fall, then 4 simulated through the landing;
# 4 cells across keeps it to 512 particles
BENCH = dict(n_frames=12, n_gaussians=2_000)


def _rows(rows, **match):
    return [r for r in rows if all(r.get(k) == v for k, v in match.items())]


def test_cfl_rows_give_the_reference_step_and_a_halved_one():
    rows = sim_options.option_table(DropBench(("jelly",), **BENCH), cells_across=4, cfls=(0.4, 0.2))
    (ref,) = _rows(rows, option="explicit")
    (same,) = _rows(rows, option="cfl_0.4")
    (half,) = _rows(rows, option="cfl_0.2")
    # the solver's own CFL number reproduces the reference exactly
    assert same["substeps"] == ref["substeps"] and same["error_px"] == 0.0
    # half the CFL number: twice the sub-steps, and a time-step error that is there but small
    assert 1.8 <= half["substeps"] / ref["substeps"] <= 2.2
    assert 0.0 < half["error_px"] < 1.0
    assert half["error_px_worst_frame"] >= half["error_px"]
    # every row says whether the planned grid held the drop (no face contact, no move)
    assert all(r["face_contacts"] == r["grid_moves"] == 0 for r in (ref, same, half))


def test_a_diverging_row_is_reported_not_raised(monkeypatch):
    real = sim_options.run_prepared

    def run(prepared):
        if prepared.solver.cfl == 0.9:
            raise SimulationDiverged("MPM diverged in frame 0 (t=0 s): det F below the floor. Materials: x")
        return real(prepared)

    monkeypatch.setattr(sim_options, "run_prepared", run)
    rows = sim_options.option_table(DropBench(("jelly",), **BENCH), cells_across=4, cfls=(0.9,))
    (row,) = _rows(rows, option="cfl_0.9")
    assert row["diverged"] == "MPM diverged in frame 0 (t=0 s): det F below the floor"
    assert "error_px" not in row


@pytest.mark.parametrize("cfl", [0.0, 1.5])
def test_cfl_rows_refuse_numbers_outside_the_solver_range(cfl):
    with pytest.raises(ValueError, match="cfl"):
        sim_options.cfl_options((cfl,))


def test_the_pressure_row_takes_fewer_steps_and_skips_plastic_models():
    rows = sim_options.option_table(DropBench(("jelly", "plasticine"), **BENCH), cells_across=4)
    (ref,) = _rows(rows, material="jelly", option="explicit")
    (split,) = _rows(rows, material="jelly", option="pressure")
    # jelly (fixed-corotated, nu = 0.45): the shear part's wave is sqrt(2 mu / (lam + 2 mu)) = 0.43 of
    # the P-wave, so about 2.3x fewer sub-steps while the landing's speed does not set the step
    assert split["substeps"] < ref["substeps"] / 1.5
    assert 0.0 < split["error_px"] < 1.0
    (skipped,) = _rows(rows, material="plasticine", option="pressure")
    assert skipped["skipped"] == "the pressure integrator does not run von_mises"
    # the default planner's choice with the integrator: what simulate.py solver.integrator=pressure runs
    (planned,) = _rows(rows, material="jelly", option="planner_pressure")
    assert planned["substeps"] <= split["substeps"] and planned["error_px"] < 1.0


def test_the_planner_row_of_a_rubber_runs_the_split_the_planner_took(monkeypatch):
    """The default planner takes the pressure split for rubber (nu = 0.48), so its row is a run of
    its own, not the same as the explicit coast row that shares its E, nu and coasting. (At 4 cells
    across the cube is under the split's PRESSURE_MIN_CELLS, lowered here to keep the test small.)"""
    from physgm.sim.planner import choose

    monkeypatch.setattr(choose, "PRESSURE_MIN_CELLS", 0.0)
    rows = sim_options.option_table(DropBench(("rubber",), **BENCH), cells_across=4, pressure=False)
    (ref,) = _rows(rows, option="explicit")
    (coast,) = _rows(rows, option="coast")
    (planner,) = _rows(rows, option="planner")
    assert (ref["integrator"], coast["integrator"], planner["integrator"]) == (
        "explicit",
        "explicit",
        "pressure",
    )
    assert "same_as" not in planner and planner["substeps"] < ref["substeps"] / 2
    assert (
        planner["error_px"] < 1.0
    )  # the landing, before the runs part (docs/measurements_sim.md section 42)
