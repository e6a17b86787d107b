"""Speed against error per planner option: the ``options`` part of ``python -m physgm.bench sim``.

For each material, the 50-frame drop of the 15 cm hollow cube runs once per planner option, all
in one process, and every option's Gaussian centres are compared with the explicit reference's
in the bench camera (256 px):

    explicit       MPM at the full E and nu (no rigid path, no caps): the reference;
    bulk_cap       shear modulus kept, nu lowered to c_p = r c_s (sim/bulk_cap.py; r = 2, or one
                   row bulk_cap_r<r> per ratio given);
    stiffness_cap  E lowered within cap_budget of the bound, also after elastic impacts;
    coast          the reference's plan with flights after a bounce in closed form (sim/coast.py);
    planner        what the default planner chooses (rigid, caps or none) under its bound;
    pressure       the explicit run's plan with lam's volume term implicit on the grid
                   (sim/mpm/pressure.py): the explicit step follows the shear part's wave. Elastic
                   models only; others are listed as skipped.
    planner_pressure
                   the default planner's choice run with the pressure integrator: what
                   ``simulate.py solver.integrator=pressure`` does.
    implicit_<dt>ms_theta<theta>
                   the explicit run's plan with the implicit elastic integrator (sim/mpm/implicit.py):
                   sub-step dt while slow, the advective limit dx / |v| when fast (cfl 1); theta 1
                   backward Euler, 0.5 midpoint. Elastic models only; others are listed as skipped.
    cfl_<c>        the explicit run's plan at another CFL number c (the default is 0.4): a smaller c
                   measures the reference's own time-step error, a larger one what fewer sub-steps
                   would cost (docs/measurements_sim.md section 13). c also sets the particle
                   friction's cap, m |v_t| / (c tau) (sim/mpm/particle_ground.py), so a row measures
                   the step and that cap together: on the rubber drop cfl 0.2 moves the first
                   contact 3.4 px, a half step with the cap kept 0.09 px (section 42).

A row gives seconds, sub-steps, the planner's predicted error and the measured error: mean over
frames and Gaussians, the worst frame's mean, and the largest single Gaussian's distance.
Options that leave the material unchanged (nu already below the cap's, a cap that saves nothing)
are listed with ``same_as`` instead of being run again. A reference whose predicted cost exceeds
``max_reference_cost`` particle-substeps is not run (the stiff materials the planner makes rigid
would take hours): its row gives the predicted cost instead.
"""

from __future__ import annotations

import sys

from physgm.bench.drop_scene import DropBench, project
from physgm.sim.gaussian_trajectory import GaussianTrajectory, prepare_simulation, run_prepared
from physgm.sim.mpm.implicit import IMPLICIT_MODELS
from physgm.sim.mpm.pressure import PRESSURE_MODELS
from physgm.sim.mpm.stepping import SimulationDiverged, SolverConfig
from physgm.sim.planner import PlannerConfig

OFF = dict(
    allow_rigid=False, allow_bulk_cap=False, allow_stiffness_cap=False, allow_pressure=False, coast=False
)


def options(bulk_ratios: tuple[float, ...] = (2.0,)) -> dict[str, dict]:
    """Option name -> planner overrides; one bulk-cap row per c_p / c_s ratio."""
    out: dict[str, dict] = {"explicit": OFF}
    for r in bulk_ratios:
        name = "bulk_cap" if len(bulk_ratios) == 1 else f"bulk_cap_r{r:g}"
        out[name] = {**OFF, "allow_bulk_cap": True, "force_caps": True, "bulk_wave_ratio": r}
    out["stiffness_cap"] = {**OFF, "allow_stiffness_cap": True, "force_caps": True}
    out["coast"] = {**OFF, "coast": True}
    out["planner"] = {}
    return out


def cfl_options(cfls: tuple[float, ...]) -> dict[str, SolverConfig]:
    """Option name -> solver settings of the CFL rows: the explicit step at CFL number c."""
    return {f"cfl_{c:g}": SolverConfig(cfl=c) for c in cfls}


# Solver integrators other than explicit -> the constitutive models each can run.
INTEGRATOR_MODELS = {"implicit": IMPLICIT_MODELS, "pressure": PRESSURE_MODELS}


def implicit_options(steps: tuple[tuple[float, float], ...]) -> dict[str, SolverConfig]:
    """Option name -> solver settings of the implicit rows; ``steps`` holds (dt s, theta) pairs."""
    return {
        f"implicit_{dt * 1e3:g}ms_theta{theta:g}": SolverConfig(
            integrator="implicit", implicit_dt=dt, implicit_theta=theta, cfl=1.0
        )
        for dt, theta in steps
    }


def errors_px(cameras, run: GaussianTrajectory, ref: GaussianTrajectory) -> dict[str, float]:
    """Projected Gaussian-centre distances to the reference, pixels: mean, worst frame, largest."""
    d = (project(cameras, run.means()) - project(cameras, ref.means())).norm(dim=-1)  # [T, N]
    return {
        "error_px": float(d.mean()),
        "error_px_worst_frame": float(d.mean(-1).max()),
        "error_px_max": float(d.max()),
    }


def option_table(
    bench: DropBench,
    max_reference_cost: float = 3e9,
    cells_across: int | None = None,
    bulk_ratios: tuple[float, ...] = (2.0,),
    implicit_steps: tuple[tuple[float, float], ...] = (),
    cfls: tuple[float, ...] = (),
    pressure: bool = True,
) -> list[dict]:
    """One row per (material, option) of the bench drop; see the module docstring.

    Args:
        max_reference_cost: particle-substeps above which the explicit reference is not run.
        cells_across: grid cells across the object for every option (None: the planner default).
        bulk_ratios: c_p / c_s of the bulk-cap rows (one row each).
        implicit_steps: (dt s, theta) of the implicit rows (one row each).
        cfls: CFL numbers of the explicit rows at another step (one row each).
        pressure: add the pressure integrator's row.
    """
    grid = {} if cells_across is None else {"cells_across": cells_across}
    gaussians, cameras, scene_overrides = bench.gaussians(), bench.camera(), bench.scene_overrides()
    out = []
    for name in bench.materials:
        physics = bench.physics(name)

        ref, seen = None, {}
        for option, overrides in options(tuple(bulk_ratios)).items():
            cfg = PlannerConfig(**overrides, **grid)
            prepared = prepare_simulation(
                gaussians, physics, "drop", cameras, bench.n_frames, cfg, scene_overrides=scene_overrides
            )
            probe = prepared.plan
            key = (probe.mode, probe.integrator, probe.E_used, probe.nu_used, cfg.coast)
            row = {"material": name, "option": option, **physics.to_dict(), **grid, "mode": probe.mode}
            row["integrator"] = probe.integrator
            row.update(E_used=probe.E_used, nu_used=probe.nu_used)
            row.update(
                substeps_per_frame=probe.substeps_per_frame, predicted_error_px=probe.predicted_error_px
            )
            if key in seen:
                out.append({**row, "same_as": seen[key]})
                continue
            seen[key] = option
            if option == "explicit" and probe.predicted_cost > max_reference_cost:
                out.append({**row, "skipped": f"predicted cost {probe.predicted_cost:.3g} particle-substeps"})
                print(f"[bench sim options] {name}: reference too costly, skipped", file=sys.stderr)
                break
            traj = run_prepared(prepared)
            row.update(seconds=traj.seconds, substeps=traj.substeps, rest_frame=traj.rest_frame)
            row.update(coasted_frames=traj.coasted_frames, coast_predicted_px=traj.coast_predicted_px)
            row.update(face_contacts=traj.face_contacts, grid_moves=traj.grid_moves)
            if option == "explicit":
                ref = traj
            row.update(errors_px(cameras, traj, ref))
            out.append(row)
            print(
                f"[bench sim options] {name} {option}: {traj.seconds:.1f} s, {row['error_px']:.3g} px",
                file=sys.stderr,
            )
        if ref is not None:
            solvers = {**cfl_options(tuple(cfls)), **implicit_options(tuple(implicit_steps))}
            if pressure:
                solvers["pressure"] = SolverConfig(integrator="pressure")
            out += _solver_rows(bench, name, gaussians, cameras, scene_overrides, grid, ref, solvers)
            if pressure:
                split = {"planner_pressure": SolverConfig(integrator="pressure")}
                out += _solver_rows(bench, name, gaussians, cameras, scene_overrides, grid, ref, split, {})
    return out


def _solver_rows(
    bench, name, gaussians, cameras, scene_overrides, grid, ref, solvers, planner=OFF
) -> list[dict]:
    """The explicit reference's plan (or the planner with ``planner``'s overrides) with other
    solver settings (``cfl_options``, ``implicit_options``, the pressure integrator), one row per
    option."""
    physics, rows = bench.physics(name), []
    for option, solver in solvers.items():
        row = {"material": name, "option": option, **physics.to_dict(), **grid, "cfl": solver.cfl}
        if solver.integrator == "implicit":
            row.update(implicit_dt=solver.implicit_dt, implicit_theta=solver.implicit_theta)
        prepared = prepare_simulation(
            gaussians,
            physics,
            "drop",
            cameras,
            bench.n_frames,
            PlannerConfig(**planner, **grid),
            solver=solver,
            scene_overrides=scene_overrides,
        )
        models = INTEGRATOR_MODELS.get(solver.integrator)
        model = prepared.material.model
        if models is not None and prepared.plan.mode != "mpm":
            rows.append({**row, "skipped": f"the planner chose {prepared.plan.mode}"})
            continue
        if models is not None and model not in models:
            rows.append({**row, "skipped": f"the {solver.integrator} integrator does not run {model}"})
            continue
        try:
            traj = run_prepared(prepared)
        except SimulationDiverged as err:  # a step past the stability limit: the row says so
            rows.append({**row, "diverged": str(err).split(". Materials")[0]})
            print(f"[bench sim options] {name} {option}: diverged", file=sys.stderr)
            continue
        row.update(seconds=traj.seconds, substeps=traj.substeps, rest_frame=traj.rest_frame)
        row.update(coasted_frames=traj.coasted_frames)
        row.update(face_contacts=traj.face_contacts, grid_moves=traj.grid_moves)
        row.update(errors_px(cameras, traj, ref))
        rows.append(row)
        print(
            f"[bench sim options] {name} {option}: {traj.seconds:.1f} s, {row['error_px']:.3g} px",
            file=sys.stderr,
        )
    return rows
