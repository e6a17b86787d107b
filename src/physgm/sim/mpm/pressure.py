"""Implicit pressure for nearly incompressible elastic solids: the explicit step keeps the shear.

A rubber (nu = 0.48) carries a pressure wave five times faster than its shear wave, and the
explicit step follows the fastest wave, so four of every five sub-steps resolve a volume change
of a fraction of a percent that no viewer sees. This integrator splits the elastic energy of
the elastic models (``fixed_corotated``, ``neo_hookean``) into the part without the first Lame
parameter lam, which the explicit sub-step (``launches``) integrates as before, and lam's part,
a function phi(J) of the volume ratio alone (``pressure_kernels.volume_terms``), which the grid
integrates implicitly. The explicit step then follows the shear part's P-wave,
sqrt(2 mu / rho): rubber at nu = 0.48 takes up to sqrt((lam + 2 mu) / (2 mu)) = 3.6x fewer sub-steps
(fewer while the body's own speed sets the step).

The implicit part (after Stomakhin et al. 2014's augmented MPM, on the MPM grid itself): each
particle adds its Kirchhoff pressure times its rest volume, V0 J phi'(J), and its volume
stiffness V0 J^2 phi''(J) to the 8 cells whose centres surround it, with trilinear weights w,
giving each cell the sums s_c and K_c. After the grid update has given the node velocities v*
(shear stress, gravity, ground contact), the velocities of the step are the minimiser of

    sum_n m_n |v_n - v*_n|^2 / 2 + h sum_c (s_c (D v)_c + theta h K_c (D v)_c^2 / 2),

the volume energy linearised about the sub-step's start and taken at theta of the way through
it, each particle's J growing by h times the w-weighted Q1 divergence D v of its cells
(``pressure_kernels``; the weights are lumped into the cells' K, which only stiffens it). That is
the linear system

    (M + theta h^2 D^T K D) v = M v* - h D^T s,

symmetric positive definite, solved for the correction v - v* by Jacobi-preconditioned
conjugate gradients over the nodes of the box of cells the particles reach (every product is a
pass over cells and nodes, not particles), started from the last two sub-steps' corrections
extrapolated linearly, and stopped at an rms velocity residual of
``SolverConfig.pressure_tolerance``. Particles then move and deform with v in g2p, which adds
their new J's terms to the cells as it goes: the next sub-step's s and K (a pass of its own,
``gather_cells``, does it only after a fresh scatter).

``SolverConfig.pressure_theta`` places the volume term. A volume wave of frequency omega keeps a
share 1 / (1 + theta (omega h)^2) of its energy a sub-step (the determinant of the step's map for
one wave): theta = 1 is backward Euler, theta = 0.5 takes the volume term at the step's middle and
damps half as fast, and every theta from 0.5 up is stable at any step (below 0.5 the waves the step
does not resolve grow once (1 - 2 theta) (omega h)^2 passes 4). The volume waves are what a landing
excites and explicit MPM, which damps none, gives back to the rebound. The default, 0.6, damps them
at about 0.6 times backward Euler's rate: 0.5 left a particle or two crushed (det F < 0.1) in the
stability matrix's impacts at twice the P-wave speed (fixed-corotated, nu = 0.49), where 0.6 and 1
leave none. Dropped 0.5 m, the bench's 15 cm rubber cube (E = 5e6 Pa, nu = 0.48) follows explicit
within 0.25 px through its first contact and rebound under any theta; its second bounce rises to
0.275 m under explicit (0.256 m at a quarter of explicit's step), 0.237 m at theta = 0.6 and
0.220 m at theta = 1 (docs/measurements_sim.md section 42).
Both stages are recorded launches inside the sub-step, so the sub-steps still replay from graphs;
the solve is one serial launch (the CPU's way of running any launch; on a GPU it is correct but
does not use the device's threads).

Scope: elastic models only; a ground with contact on the particles (the default) or none; no
velocity boxes, side walls or periodic axes (their node conditions would fight the solve).
Anything else raises a ValueError that says to run explicit. Its grid arrays add about 120 bytes
a node to the explicit solver's 96.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from physgm.sim.constitutive import MaterialParams, MaterialStruct
from physgm.sim.mpm import particle_ops as ops
from physgm.sim.mpm import pressure_kernels as PK
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.solver import MPMSolver
from physgm.sim.mpm.spin_barrier import LIMIT_CYCLES, YIELD_AFTER_CYCLES, new_counter
from physgm.sim.mpm.state import Particles
from physgm.sim.mpm.stepping import SolverConfig, step_wave_speed
from physgm.warp_runtime import ensure_loaded

PRESSURE_MODELS = ("fixed_corotated", "neo_hookean")  # phi(J) carries lam alone in these


def shear_part(material: MaterialParams) -> MaterialParams:
    """The material without lam: the same shear modulus at nu = 0 (E = 2 mu), which the explicit
    sub-step runs. Its P-wave speed sqrt(2 mu / rho) sets the step."""
    return material.with_elasticity(E=2.0 * material.mu, nu=0.0)


# What a sub-step of this integrator costs over an explicit one on the same body, the
# conjugate-gradient solve included: on the AVX2 host of docs/measurements_sim.md section 27, two
# threads, 2.12 on the bench's 50-frame rubber drop (13,824 particles) and 2.04 on
# `simulate.py input=examples/basketball.png` (2,944 particles), measured the same hour (section 45;
# 1.64-1.82 in session 63). The planner takes the split only where it saves sub-steps by
# ``planner.min_cap_gain`` times this (``planner.allow_pressure``).
PRESSURE_STEP_COST = 2.1

# Grid cells the body must span in its thinnest direction for the planner to take the split. The
# split's volume term lives on the grid's cells, and a body few cells thick resolves it poorly: the
# bench's rubber drop (E = 5e6 Pa, nu = 0.48) with the cube squashed to a slab drifted from explicit
# through its first contact by at most 0.21 px at 12 cells thick, 1.42 px at 9, 1.68 px at 6 and
# 2.58 px at 3 (frames 0-18), where explicit's own half step moved 0.09-0.89 px; at 10.5 cells, 0.26
# px there and 1.50 px in frames 19-20 (docs/measurements_sim.md section 45).
PRESSURE_MIN_CELLS = 12.0


def thinnest_extent(x: np.ndarray, spacing: float) -> float:
    """The body's smallest extent, m: the least of its extents along the axes and along its principal
    axes (a slab turned off the axes), the particles' centres plus one lattice spacing."""
    x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    centred = x - x.mean(0)
    axes = np.linalg.eigh(centred.T @ centred)[1]
    extents = np.concatenate([np.ptp(x, axis=0), np.ptp(centred @ axes, axis=0)])
    return float(extents.min()) + spacing


def scene_extras(scene: Scene) -> list[str]:
    """What in ``scene`` the pressure split does not handle (empty when it handles the scene)."""
    ground = scene.ground
    extras = {
        "velocity boxes": bool(scene.boxes),
        "side walls": bool(scene.walls),
        "periodic axes": bool(scene.periodic),
        "a ground held on the grid nodes": ground is not None and not ground.on_particles,
    }
    return [name for name, present in extras.items() if present]


def check_pressure(materials: Sequence[MaterialParams], scene: Scene) -> None:
    """Raise ValueError for what the pressure split does not handle, saying what to do instead."""
    unsupported = sorted({m.model for m in materials} - set(PRESSURE_MODELS))
    if unsupported:
        raise ValueError(
            f"the pressure integrator handles the elastic models {', '.join(PRESSURE_MODELS)} only, "
            f"not {', '.join(unsupported)}; run them with integrator='explicit'"
        )
    named = scene_extras(scene)
    if named:
        raise ValueError(
            f"the pressure integrator supports gravity and a ground with contact on the particles only, "
            f"not {', '.join(named)}; run this scene with integrator='explicit'"
        )


@dataclass(frozen=True)
class PressureCounters:
    """The solves so far: how many, their conjugate-gradient iterations, and how many stopped at
    ``pressure_max_iterations`` above the tolerance."""

    solves: int
    iterations: int
    unconverged: int


class PressureStep:
    """The grid stage of the pressure split (module docstring): each thread's particles add their
    volume terms to the cells, in g2p for the next sub-step (``kernels.g2p_kernel(...,
    pressure=True)``) or, after a fresh scatter, in a pass of their own
    (``pressure_kernels.gather_cells``), then each thread solves its half of the grid's layers for
    the node velocities, the two meeting at a barrier between passes (``pressure_kernels.solve``,
    after the grid update). All are recorded launches that ``SubstepLaunches`` runs; the solve is
    inside every sub-step and its graphs."""

    def __init__(self, solver: MPMSolver, materials: wp.array) -> None:
        dev, res, g, ps = solver.device, solver.grid.res, solver.grid, solver.particles
        threads, cfg = solver.threads, solver.config
        self.cell_s = [wp.zeros(res, dtype=float, device=dev) for _ in range(threads)]
        self.cell_k = [wp.zeros(res, dtype=float, device=dev) for _ in range(threads)]
        none = wp.zeros((1, 1, 1), dtype=float, device=dev)  # one thread: no second sums
        self._empty = np.tile([PK.BOX_EMPTY] * 3 + [-PK.BOX_EMPTY] * 3, (threads, 1)).astype(np.int32)
        self.box = wp.array(self._empty, dtype=wp.int32, device=dev)
        self.t, self.mass, self.diag = (wp.zeros(res, dtype=float, device=dev) for _ in range(3))
        vectors = (wp.zeros(res, dtype=wp.vec3, device=dev) for _ in range(6))
        self.d, self.r, self.z, self.p, self.q, self.w = vectors
        self.d_stamp = wp.zeros(res, dtype=wp.int32, device=dev)
        self.d_old = wp.zeros(res, dtype=wp.vec3, device=dev)
        self.old_stamp = wp.full(res, -1, dtype=wp.int32, device=dev)
        self.stats = wp.zeros(3, dtype=wp.float64, device=dev)  # float64: counts stay exact
        ensure_loaded(PK.gather_cells, dev)
        n = solver.num_particles
        split = [0, n] if threads == 1 else [0, n // 2, n]
        self.gathers = [
            wp.launch(
                PK.gather_cells,
                split[t + 1] - split[t],
                [ps.x, ps.H, ps.vol0, materials, ps.material, wp.vec3(*g.origin), g.dx, split[t], t]
                + [self.cell_s[t], self.cell_k[t], self.box],
                device=dev,
                record_cmd=True,
            )
            for t in range(threads)
        ]
        s1, k1 = (self.cell_s[1], self.cell_k[1]) if threads == 2 else (none, none)
        # The solve's halves meet at the sub-step's own barrier, whose abandonment the launches check
        # (``spin_barrier``); one thread never waits.
        meeting = solver.launches.meeting if threads == 2 else new_counter(dev)
        self.partial = wp.zeros((2, 4), dtype=wp.float64, device=dev)
        self.solves = [
            wp.launch(
                PK.solve,
                1,
                [slot, threads, meeting, wp.vec2l(LIMIT_CYCLES, YIELD_AFTER_CYCLES), solver.grid_v]
                + [self.cell_s[0], self.cell_k[0], s1, k1, self.box, solver.launches.params]
                + [cfg.pressure_tolerance, cfg.pressure_max_iterations, cfg.pressure_theta, self.partial]
                + [self.t, self.mass, self.diag, self.d, self.r, self.z, self.p, self.q, self.w]
                + [self.d_stamp, self.d_old, self.old_stamp, self.stats, g.dx],
                device=dev,
                record_cmd=True,
            )
            for slot in range(threads)
        ]

        # What g2p adds its particles' volume terms to (``SubstepLaunches.set_grid_stage``).
        lam = wp.array([m.lam for m in solver.materials], dtype=float, device=dev)
        self.cells = (lam, self.cell_s, self.cell_k, self.box)

    def clear(self) -> None:
        """Drop the sums the last g2p left: the particle state they came from was replaced."""
        for a in (*self.cell_s, *self.cell_k):
            a.zero_()
        self.box.assign(self._empty)

    def counters(self) -> PressureCounters:
        return PressureCounters(*(int(x) for x in self.stats.numpy()))


class PressureSplitMPMSolver(MPMSolver):
    """``MPMSolver`` with lam's volume term taken implicitly on the grid (module docstring); same
    arguments (the solve's tolerance is ``config.pressure_tolerance``). ``pressure.counters()``
    sums up the solves so far.
    ``materials`` stays the full materials (and ``energy()`` reports their energy); the explicit
    step runs their ``shear_part``."""

    def __init__(
        self,
        particles: Particles,
        materials: Sequence[MaterialParams],
        grid: GridSpec,
        scene: Scene | None = None,
        config: SolverConfig | None = None,
        device: str | wp.Device | None = "cpu",
    ) -> None:
        scene = scene or Scene()
        check_pressure(materials, scene)
        super().__init__(particles, materials, grid, scene, config, device)
        ps = self.particles
        # The full materials: the grid's volume term takes their lam whole (the shear part has none),
        # and energy() reports their energy.
        self.energy_table = wp.clone(ps.mat_table)
        shear = [shear_part(m) for m in self.materials]
        wp.copy(ps.mat_table, wp.array([m.pack() for m in shear], dtype=MaterialStruct, device=self.device))
        wp.launch(
            ops.init_stress,
            self.num_particles,
            [ps.H, ps.mat_table, ps.material, ps.vol0, ps.plastic, ps.stress],
            device=self.device,
        )
        self.pressure = PressureStep(self, self.energy_table)
        self.launches.set_grid_stage(self.pressure.gathers, self.pressure.solves, self.pressure.cells)
        self.launches.on_invalidate.append(self.pressure.clear)
        self._c_max = step_wave_speed(shear, self.scene, particles, self.grid.dx)
        self._fit_active(self.stable_dt())
