"""``python -m physgm.bench sim-substep``: the cost of one small MPM sub-step, per stepping mode.

A block of P particles (8 per cell) resting on the ground is stepped through ``step_frame`` with
each mode in turn, in one process, round after round, so that the host's load swings hit every
mode alike:

    python:   one thread, each sub-step's launches from Python (``SolverConfig(graphs=False)``);
    graph:    one thread, runs of ``cfl_check_every`` sub-steps replayed from a captured launch
              graph (``graphs=True``, the default);
    threads2_python: two threads, each sub-step's launches from Python, handed off through a lock
              (``graphs=False``);
    threads2: two threads, each replaying its half's graph, meeting at spin barriers (the
              default, ``launches.run_graph``).

Prints one JSON object: per material and size, the median microseconds per sub-step of each mode,
wall-clock (with the spread over the rounds) and CPU time (``_cpu_us``: the process's, so for
the threads2 modes the sum over both threads), the median of the per-round ratios python / graph of each,
and a least-squares fit us = fixed + per_particle x P per mode over the sizes. The file also runs as a
script against a tree without graph replay (``PYTHONPATH=<tree>/src python sim_substep.py``),
which then times the modes it has. Wall-clock on a shared CPU; nothing asserts on it.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from dataclasses import fields

import numpy as np
import warp as wp

from physgm.physics.materials import get_material
from physgm.sim.mpm import GridSpec, GroundPlane, MPMSolver, Particles, Scene, SolverConfig, cfl_dt

E_BENCH = {"jelly": 1e5}  # the jelly of the drop benchmark (the table default is 1e4 Pa)
SIDE = 0.1  # m, block edge
MODES = {
    "python": dict(threads=1, graphs=False),
    "graph": dict(threads=1, graphs=True),
    "threads2_python": dict(threads=2, graphs=False),
    "threads2": dict(threads=2, graphs=True),
}


def block(n: int) -> tuple[Particles, float]:
    """A lattice block of about ``n`` particles (k x k x round(n / k^2) layers, k = round(n^(1/3)),
    spacing SIDE / k) a cell above the ground, and the grid spacing that puts 8 of them in a cell."""
    k = round(n ** (1 / 3))
    spacing = SIDE / k
    layers = max(1, round(n / k**2))
    lo = np.array([0.0, 0.0, 2.0 * spacing])  # one cell up: it falls a cell and lands
    particles = Particles.lattice(lo, lo + np.array([SIDE, SIDE, layers * spacing]), spacing)
    return particles, 2.0 * spacing


def time_mode(particles: Particles, dx: float, material, mode: dict, substeps: int) -> tuple[float, float]:
    """Wall-clock and CPU (process, all threads) microseconds per sub-step of ``step_frame`` over
    frames of ~256 sub-steps (the README demo takes ~317 a frame), after one warm-up frame (which
    also captures the graph). On a shared CPU the wall clock also counts the time other jobs held
    the core; the CPU time does not."""
    frame_dt = 256 * cfl_dt(dx, [material], 0.0, SolverConfig().cfl)
    known = {f.name for f in fields(SolverConfig)}
    config = SolverConfig(frame_dt=frame_dt, **{k: v for k, v in mode.items() if k in known})
    grid = GridSpec.fit((-0.05, -0.05, 0.0), (SIDE + 0.05, SIDE + 0.05, SIDE + 0.05), dx)
    solver = MPMSolver(particles, [material], grid, Scene(ground=GroundPlane()), config)
    try:
        solver.step_frame()
        steps, start, cpu = 0, time.perf_counter(), time.process_time()
        while steps < substeps:
            steps += solver.step_frame().substeps
        return 1e6 * (time.perf_counter() - start) / steps, 1e6 * (time.process_time() - cpu) / steps
    finally:
        solver.close()


def fit(sizes: list[int], us: list[float]) -> dict[str, float]:
    """us = fixed + per_particle x P, least squares."""
    per_particle, fixed = np.polyfit(np.asarray(sizes, float), np.asarray(us, float), 1)
    return {"fixed_us": round(float(fixed), 1), "per_particle_us": round(float(per_particle), 4)}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(
        prog="python -m physgm.bench sim-substep", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=[649, 2000, 8000])
    parser.add_argument("--materials", nargs="+", default=["jelly", "rubber"])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--substeps", type=int, default=512, help="timed sub-steps per mode and round")
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    args = parser.parse_args(argv)
    wp.config.quiet = True
    has_graphs = "graphs" in {f.name for f in fields(SolverConfig)}
    modes = [m for m in args.modes if has_graphs or m != "graph"]
    rows = []
    for name in args.materials:
        spec = get_material(name)
        material = spec.params(E=E_BENCH.get(name, spec.E))
        for n in args.sizes:
            particles, dx = block(n)
            wall: dict[str, list[float]] = {m: [] for m in modes}
            cpu: dict[str, list[float]] = {m: [] for m in modes}
            for _ in range(args.rounds):
                for m in modes:
                    w, c = time_mode(particles, dx, material, MODES[m], args.substeps)
                    wall[m].append(w)
                    cpu[m].append(c)
            row = {"material": name, "E": material.E, "particles": len(particles), "dx": round(dx, 5)}
            for m in modes:
                row[f"{m}_us"] = round(statistics.median(wall[m]), 1)
                row[f"{m}_us_range"] = [round(min(wall[m]), 1), round(max(wall[m]), 1)]
                row[f"{m}_cpu_us"] = round(statistics.median(cpu[m]), 1)
            if "python" in modes and "graph" in modes:
                for key, t in (("python_over_graph", wall), ("python_over_graph_cpu", cpu)):
                    ratios = [a / b for a, b in zip(t["python"], t["graph"], strict=True)]
                    row[key] = round(statistics.median(ratios), 3)
            rows.append(row)
    fits = {}
    for name in args.materials:
        mine = [r for r in rows if r["material"] == name]
        if len(mine) >= 2:
            sizes = [r["particles"] for r in mine]
            fits[name] = {
                f"{m}{kind}": fit(sizes, [r[f"{m}{kind}_us"] for r in mine])
                for m in modes
                for kind in ("", "_cpu")
            }
    result = {
        "rows": rows,
        "fits": fits,
        "rounds": args.rounds,
        "substeps_per_timing": args.substeps,
        "loadavg": [round(x, 2) for x in os.getloadavg()],
        "cpu_note": "wall-clock on a shared 2-core CPU: compare modes within a row (same rounds), not runs",
    }
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
