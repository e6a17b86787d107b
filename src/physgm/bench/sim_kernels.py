"""Each MPM kernel against the memory limit: the ``kernels`` part of ``python -m physgm.bench sim``.

A jelly block of P particles (8 per cell) resting on the ground, on one thread; each part is the
fastest of ``repeats``:

    p2g          the scatter of a fresh particle state (the first sub-step, and after a retry),
                 its launch alone;
    grid_update  accumulators -> node velocities, timed inside real sub-steps (between the
                 hooks ``SubstepLaunches.run`` calls around it);
    g2p          gather, F update and stress, advection, and the scatter for the next sub-step,
                 its launch alone (repeating it keeps a resting block at rest);
    substep      ``MPMSolver.substep``: grid_update, g2p and the host's work between sub-steps.

For the particle kernels a row gives the particle-array bytes the kernel reads and writes per
particle (from the solver's own arrays), the bandwidth that implies, and its share of the host's
copy bandwidth (numpy copying a 256 MB array, reads plus writes): the memory limit of a kernel
that streams its particles once. The grid, a few MB that stay in cache, is not counted. A steady
sub-step streams what g2p streams, so its limit is the copy bandwidth over g2p's bytes. Wall-clock
on a shared CPU; nothing asserts on it.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import warp as wp

from physgm.physics.materials import get_material
from physgm.sim.mpm import GridSpec, GroundPlane, MPMSolver, Particles, Scene, SolverConfig

COPY_BYTES = 256 * 2**20


def _fastest(fn: Callable[[], object], repeats: int, device: str) -> float:
    """The fastest of ``repeats`` calls of ``fn``, s."""
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        wp.synchronize_device(device)
        best = min(best, time.perf_counter() - start)
    return best


def copy_bandwidth(repeats: int = 5) -> float:
    """Bytes per second numpy moves copying a 256 MB array (read + write), the fastest of ``repeats``."""
    src = np.ones(COPY_BYTES // 4, np.float32)
    dst = np.empty_like(src)
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        np.copyto(dst, src)
        best = min(best, time.perf_counter() - start)
    return 2 * COPY_BYTES / best


def _bytes(arrays: list[wp.array]) -> int:
    """Bytes per particle of these per-particle arrays."""
    return sum(wp.types.type_size_in_bytes(a.dtype) for a in arrays)


def particle_bytes(solver: MPMSolver) -> dict[str, int]:
    """Particle-array bytes per particle that p2g and g2p read and write (their kernel arguments)."""
    ps = solver.particles
    return {
        "p2g": _bytes([ps.x, ps.v, ps.C, ps.stress, ps.mass, ps.vol0, ps.material]),
        "g2p": _bytes([ps.x, ps.v, ps.C, ps.H, ps.plastic, ps.escaped, ps.material, ps.vol0, ps.mass])
        + _bytes([ps.x, ps.v, ps.C, ps.H, ps.stress, ps.plastic]),
    }


def resting_block(n: int, config: SolverConfig, device: str, jelly_E: float = 1e5) -> MPMSolver:
    """The throughput block: a 20 cm jelly cube of about ``n`` particles (8 per cell) on the ground."""
    side = 0.2
    spacing = side / round(n ** (1 / 3))
    particles = Particles.lattice((-side / 2, -side / 2, 0.0), (side / 2, side / 2, side), spacing)
    grid = GridSpec.fit((-side / 2, -side / 2, 0.0), (side / 2, side / 2, side * 1.2), 2 * spacing)
    material = get_material("jelly").params(E=jelly_E)
    return MPMSolver(particles, [material], grid, Scene(ground=GroundPlane()), config, device)


def kernel_shares(n: int = 200_000, device: str = "cpu", repeats: int = 20, jelly_E: float = 1e5) -> dict:
    """Per-kernel times and shares of the copy bandwidth; see the module docstring."""
    solver = resting_block(n, SolverConfig(threads=1, graphs=False), device, jelly_E)
    p, grid_nodes = solver.num_particles, solver.grid.num_nodes
    try:
        dt = solver.stable_dt()
        for _ in range(3):  # warm-up: compiled, scattered, active box fitted
            solver.substep(dt)
        launches = solver.launches
        substep = _fastest(lambda: solver.substep(dt), repeats, device)
        marks: list[float] = []
        grid_update = np.inf
        for _ in range(repeats):  # a real sub-step each, grid_update between its two hooks
            launches.run(
                None, lambda: marks.append(time.perf_counter()), lambda: marks.append(time.perf_counter())
            )
            grid_update = min(grid_update, marks[-1] - marks[-2])
        seconds = {"grid_update": grid_update, "g2p": _fastest(launches.g2p[0].launch, repeats, device)}
        seconds["p2g"] = _fastest(launches.p2g[0].launch, repeats, device)  # last: it piles up the grid
        per_particle = particle_bytes(solver)
    finally:
        solver.close()
    bandwidth = copy_bandwidth()
    rows = []
    seconds["substep"] = substep
    for name in ("p2g", "grid_update", "g2p", "substep"):
        row = {"kernel": name, "ms": 1e3 * seconds[name], "ns_per_particle": 1e9 * seconds[name] / p}
        if name in per_particle:
            rate = per_particle[name] * p / seconds[name]
            row.update(bytes_per_particle=per_particle[name], GB_per_s=rate / 1e9)
            row["share_of_copy"] = rate / bandwidth
        rows.append(row)
    limit = bandwidth / per_particle["g2p"]
    return {
        "particles": p,
        "grid_nodes": grid_nodes,
        "copy_GB_per_s": bandwidth / 1e9,
        "kernels": rows,
        "substep_particle_substeps_per_s": p / substep,
        "memory_limit_particle_substeps_per_s": limit,
        "substep_share_of_limit": (p / substep) / limit,
    }
