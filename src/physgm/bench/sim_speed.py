"""``python -m physgm.bench sim``: simulator throughput, planned drops per material, speed vs error.

Prints one JSON object:
    throughput:     raw MPM solver particle-substeps per second at 10k / 50k / 200k particles;
    kernels:        each kernel of a sub-step at 200k particles on one thread, against the memory
                    limit (the host's copy bandwidth over the bytes each particle streams;
                    bench/sim_kernels.py);
    scenes:         a 50-frame drop of a ~20k-Gaussian hollow cube per material, through the planner;
    speed_vs_error: wall time against the visual error (mean Gaussian-centre distance in pixels at
                    the output camera, averaged over frames) relative to a fine reference run, for
                    the grid resolution, the particle density (particles per cell), the CFL
                    number and the planner on / off; every row names its particles_per_cell;
    options:        per material, seconds and pixel error (mean, worst frame, largest) of each
                    planner option, of the pressure integrator (unless ``--no-pressure``), of the
                    implicit elastic integrator (``--implicit``) and of the explicit step at other
                    CFL numbers (``--cfls``), against
                    the explicit full-stiffness reference for the same drop as ``scenes``
                    (bench/sim_options.py).
Wall-clock numbers are noisy when other jobs share the CPU; nothing here asserts on them.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import torch
import warp as wp

from physgm.bench.drop_scene import DropBench, bench_camera, hollow_cube_gaussians, project
from physgm.bench.sim_kernels import kernel_shares, resting_block
from physgm.bench.sim_options import option_table
from physgm.cameras import Cameras
from physgm.physics.materials import MATERIAL_NAMES, PhysicsSpec
from physgm.sim.gaussian_trajectory import GaussianTrajectory, simulate
from physgm.sim.mpm.boundary import GroundPlane
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.stepping import SolverConfig
from physgm.sim.planner import PlannerConfig

# The jelly of the performance target (the throughput blocks and the drop): E = 1e5 Pa; the
# material table's default is 1e4.
JELLY_E = 1e5
PARTS = ("throughput", "kernels", "scenes", "speed_vs_error", "options")  # all run by default


def pixel_error(cameras: Cameras, a: GaussianTrajectory, b: GaussianTrajectory) -> dict[str, float]:
    """Projected Gaussian-centre distance in pixels: mean over all frames and the worst frame's mean."""
    per_frame = (project(cameras, a.means()) - project(cameras, b.means())).norm(dim=-1).mean(-1)  # [T]
    return {"error_px": float(per_frame.mean()), "error_px_worst_frame": float(per_frame.max())}


FRAME_SUBSTEPS = 160  # sub-steps of each ``step_frame`` the throughput rows time


def throughput(sizes: list[int], substeps: int, device: str, repeats: int = 15) -> list[dict]:
    """Raw solver speed: a jelly block resting on the ground, 8 particles per cell, 1 and 2 threads.

    Each size runs ``repeats`` blocks of ``substeps`` sub-steps; the row gives the median block and
    the spread (min, max), because a shared CPU makes single timings swing by tens of percent. The
    blocks call ``substep`` (every sub-step launched from Python); ``frames_particle_substeps_per_s``
    is the median over frames of FRAME_SUBSTEPS sub-steps through ``step_frame``, the path a
    simulation takes (graph replay, CFL checks, statistics, the per-frame particle sort and backup;
    the README demo's frames take ~300), one after every fifth block.
    """
    out = []
    for n, threads in [(n, t) for n in sizes for t in (1, 2)]:
        solver = resting_block(n, SolverConfig(threads=threads), device, JELLY_E)
        count, grid = solver.num_particles, solver.grid
        blocks, frames = [], []
        try:
            dt = solver.stable_dt()
            for _ in range(3):  # warm-up (first launch, caches)
                solver.substep(dt)
            frame_dt = FRAME_SUBSTEPS * dt * (1.0 - 1e-6)  # that many CFL steps while at rest
            solver.step_frame(frame_dt)  # warm-up: captures the graphs
            for block in range(repeats):
                start = time.perf_counter()
                for _ in range(substeps):
                    solver.substep(dt)
                blocks.append((time.perf_counter() - start) / substeps)
                if block % 5 == 0:
                    start = time.perf_counter()
                    taken = solver.step_frame(frame_dt).substeps
                    frames.append((time.perf_counter() - start) / taken)
        finally:
            solver.close()
        rates = sorted(count / b for b in blocks)
        out.append(
            {
                "particles": count,
                "grid": list(grid.res),
                "grid_nodes": grid.num_nodes,
                "threads": solver.threads,
                "particle_substeps_per_s": statistics.median(rates),
                "particle_substeps_per_s_min": rates[0],
                "particle_substeps_per_s_max": rates[-1],
                "ms_per_substep": 1e3 * statistics.median(blocks),
                "frames_particle_substeps_per_s": statistics.median(count / f for f in frames),
                "repeats": repeats,
            }
        )
    return out


def drop_scenes(bench: DropBench) -> list[dict]:
    """A planned drop per material."""
    gaussians, cameras, scene_overrides = bench.gaussians(), bench.camera(), bench.scene_overrides()
    out = []
    for name in bench.materials:
        physics = bench.physics(name)
        traj = simulate(
            gaussians, physics, "drop", cameras, n_frames=bench.n_frames, scene_overrides=scene_overrides
        )
        plan = traj.plan
        out.append(
            {
                "material": name,
                "E": physics.E,
                "mode": plan.mode,
                "integrator": plan.integrator,
                "E_used": plan.E_used,
                "particles": len(traj.particles),
                "grid": plan.summary()["grid_cells"],
                "substeps": traj.substeps,
                "ballistic_frames": traj.ballistic_frames,
                "coasted_frames": traj.coasted_frames,
                "rest_frame": traj.rest_frame,
                # 0 and 0 when the planned grid held the drop; moves: the grid followed the body
                "face_contacts": traj.face_contacts,
                "grid_moves": traj.grid_moves,
                "predicted_error_px": plan.predicted_error_px,
                "seconds": traj.seconds,
            }
        )
        print(f"[bench sim] {name}: {plan.mode} {traj.seconds:.1f} s", file=sys.stderr)
    return out


def _row(
    study: str,
    physics: PhysicsSpec,
    run: GaussianTrajectory,
    ref: GaussianTrajectory | None,
    cameras,
    **extra,
) -> dict:
    plan = run.plan
    row = {
        "study": study,
        **physics.to_dict(),
        **extra,
        "mode": plan.mode,
        "E_used": plan.E_used,
    }
    row.update(
        {
            "particles": len(run.particles),
            "particles_per_cell_measured": len(run.particles)
            * plan.dx**3
            / float(run.particles.volume.sum()),
            "grid_cells": plan.summary()["grid_cells"],
            "substeps": run.substeps,
        }
    )
    row.update({"seconds": run.seconds, "predicted_error_px": plan.predicted_error_px})
    row.update(
        pixel_error(cameras, run, ref) if ref is not None else {"error_px": 0.0, "error_px_worst_frame": 0.0}
    )
    print(f"[bench sim] {study} {physics.to_dict()} {extra}: {run.seconds:.1f} s", file=sys.stderr)
    return row


def speed_vs_error(n_frames: int, n_gaussians: int, side: float, bottom: float, quick: bool) -> list[dict]:
    """Error of cheaper settings against a finer reference run, and their wall time.

    Grid, density and CFL: a soft jelly drop against a run with a finer grid and half the CFL
    number at the default density.
    Planner on / off: "off" simulates everything at full stiffness with explicit MPM, no rigid
    path, no ballistic prefix and no early stop (for the jelly also in a fixed 1 m cube instead of the
    fitted grid); "on" is the default planner, and its error is measured against "off".
    """
    gaussians = hollow_cube_gaussians(n_gaussians, side, bottom, seed=1)
    cameras = bench_camera(side, bottom)
    scene = Scene(ground=GroundPlane(0.0, friction=0.3))
    base = PlannerConfig()

    def run(physics: PhysicsSpec, cfl: float = 0.4, **planner) -> GaussianTrajectory:
        cfg = PlannerConfig(**planner)
        return simulate(
            gaussians, physics, scene, cameras, n_frames=n_frames, planner=cfg, solver=SolverConfig(cfl=cfl)
        )

    jelly = PhysicsSpec("jelly", E=2e4)
    ref_cells = 20 if quick else 24
    ref = run(jelly, cfl=0.2, cells_across=ref_cells)
    ppc = base.particles_per_cell
    out = [
        _row("reference", jelly, ref, None, cameras, cells_across=ref_cells, cfl=0.2, particles_per_cell=ppc)
    ]
    for cells in [8, 12, 16]:
        traj = run(jelly, cells_across=cells)
        out.append(
            _row("grid", jelly, traj, ref, cameras, cells_across=cells, cfl=0.4, particles_per_cell=ppc)
        )
    for density in [1.0, 8.0] if quick else [1.0, 4.0, 8.0, 27.0]:
        traj = run(jelly, particles_per_cell=density)
        settings = dict(cells_across=base.cells_across, cfl=0.4, particles_per_cell=density)
        out.append(_row("density", jelly, traj, ref, cameras, **settings))
    for cfl in [0.2, 0.4, 0.8]:
        traj = run(jelly, cfl=cfl)
        out.append(
            _row(
                "cfl",
                jelly,
                traj,
                ref,
                cameras,
                cells_across=base.cells_across,
                cfl=cfl,
                particles_per_cell=ppc,
            )
        )
    naive = dict(
        allow_rigid=False, allow_stiffness_cap=False, allow_pressure=False, ballistic=False, rest_frames=10**6
    )
    cases = [(jelly, {**naive, "fit_grid": False}), (PhysicsSpec("rubber"), naive)]
    if not quick:
        cases.append((PhysicsSpec("plastic", E=5e7), naive))
    for physics, off_cfg in cases:
        off = run(physics, **off_cfg)
        out.append(_row("planner", physics, off, None, cameras, planner="off", particles_per_cell=ppc))
        out.append(_row("planner", physics, run(physics), off, cameras, planner="on", particles_per_cell=ppc))
    return out


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m physgm.bench sim", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smaller sizes and fewer frames (a smoke run)")
    parser.add_argument(
        "--only",
        choices=PARTS,
        action="append",
        help="run only these parts (repeatable)",
    )
    parser.add_argument("--materials", nargs="*", default=list(MATERIAL_NAMES))
    parser.add_argument("--frames", type=int, default=50)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--cells", type=int, default=None, help="options: grid cells across the object")
    parser.add_argument(
        "--bulk-ratios", type=float, nargs="+", default=[2.0], help="options: c_p / c_s of the bulk-cap rows"
    )
    parser.add_argument(
        "--implicit",
        nargs="*",
        default=["2:0.5"],
        metavar="DT_MS:THETA",
        help="options: implicit rows, sub-step in ms and theta (1 backward Euler, 0.5 midpoint); "
        "the default is the row nearest the bound in docs/measurements_sim.md section 10",
    )
    parser.add_argument(
        "--cfls",
        type=float,
        nargs="*",
        default=[],
        help="options: explicit rows at these CFL numbers (the solver's is 0.4); 0.2 halves the reference's "
        "step and doubles its particle friction's cap (docs/measurements_sim.md section 42), at twice the "
        "reference's cost",
    )
    parser.add_argument(
        "--no-pressure", action="store_true", help="options: leave out the pressure integrator's rows"
    )
    args = parser.parse_args(argv)
    parts = set(args.only or PARTS)
    torch.set_num_threads(2)
    wp.config.log_level = wp.LOG_WARNING  # Warp's banner would break the one-JSON-object output
    drop = DropBench(tuple(args.materials), 10 if args.quick else args.frames, E_override={"jelly": JELLY_E})
    result: dict = {"cpu_note": "wall-clock on a shared 2-core CPU; other jobs may slow it by up to ~2x"}
    if "throughput" in parts:
        sizes = [10_000, 50_000] if args.quick else [10_000, 50_000, 200_000]
        result["throughput"] = throughput(
            sizes, substeps=10 if args.quick else 20, device=args.device, repeats=3 if args.quick else 15
        )
    if "kernels" in parts:
        result["kernels"] = kernel_shares(20_000 if args.quick else 200_000, args.device)
    if "scenes" in parts:
        result["scenes"] = drop_scenes(drop)
    if "options" in parts:
        implicit = tuple(
            (float(dt) * 1e-3, float(theta)) for dt, theta in (s.split(":") for s in args.implicit)
        )
        result["options"] = option_table(
            drop, 3e9, args.cells, tuple(args.bulk_ratios), implicit, tuple(args.cfls), not args.no_pressure
        )
    if "speed_vs_error" in parts:
        frames = 10 if args.quick else 25
        result["speed_vs_error"] = speed_vs_error(frames, drop.n_gaussians, drop.side, 0.3, args.quick)
    print(json.dumps(result, indent=1, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))
    return result


if __name__ == "__main__":
    main()
