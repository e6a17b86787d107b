"""The implicit step's solve: Newton with a Jacobi-preconditioned conjugate gradient, a
backtracking line search on the energy, and the ground's active set (``implicit.py``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from physgm.sim.mpm import implicit_algebra as LA
from physgm.sim.mpm import implicit_kernels as IK
from physgm.sim.mpm.boundary import no_ground
from physgm.warp_runtime import ensure_loaded

if TYPE_CHECKING:
    from physgm.sim.mpm.solver import MPMSolver


@dataclass(frozen=True)
class NewtonSettings:
    """Convergence settings of the per-step minimisation."""

    tolerance: float = 1.0e-3  # m/s, mass-weighted RMS of the residual m^-1 dE/du that ends Newton
    relative_tolerance: float = 1.0e-5  # or this fraction of the step's first residual
    max_newton: int = 12  # Newton iterations per sub-step, all active-set rounds together
    max_cg: int = 400  # CG iterations per Newton iteration
    cg_tolerance: float = 1.0e-2  # CG stops at this fraction of the Newton residual's norm
    max_halvings: int = 12  # line-search step halvings before the iteration gives up
    max_contact_rounds: int = 4  # re-solves after the ground's active set changed


@dataclass(frozen=True)
class SolveStats:
    """One sub-step's minimisation."""

    time: float  # s, at the start of the sub-step
    dt: float  # s
    nodes: int  # grid nodes in the solve
    newton: int  # Newton iterations
    products: int  # Hessian-vector products: each costs about one explicit sub-step
    gradients: int  # gradient evaluations (line search included), about as costly
    contact_changes: int  # ground nodes released or held after a solve
    residual: float  # m/s, final mass-weighted RMS residual
    first_residual: float  # m/s, at the predictor
    converged: bool  # the residual met a tolerance (else the iterations or the line search ran out)


_VEC_FIELDS = ("u", "u0", "target", "v_transfer", "free", "grad", "d", "r", "z", "p", "q")


class ImplicitStep:
    """The grid hook that replaces grid_update's velocities by the minimiser (``implicit.py``).

    Dense [nx, ny, nz] work arrays are allocated once; every pass runs over the nodes that hold
    mass this sub-step (``nodes``) and the particles.
    """

    def __init__(self, solver: MPMSolver, theta: float, settings: NewtonSettings) -> None:
        self.theta, self.settings = theta, settings
        dev, res = solver.device, solver.grid.res
        ensure_loaded(IK.gradient_pass, dev)
        ensure_loaded(LA.cg_start, dev)
        vec = {name: wp.zeros(res, dtype=wp.vec3, device=dev) for name in _VEC_FIELDS}
        self.u, self.u0, self.target, self.v_transfer, self.free = (vec[n] for n in _VEC_FIELDS[:5])
        self.grad, self.d, self.r, self.z, self.p, self.q = (vec[n] for n in _VEC_FIELDS[5:])
        self.mass = wp.zeros(res, dtype=float, device=dev)  # kg
        self.diag = wp.zeros(res, dtype=float, device=dev)  # kg, elastic Hessian diagonal estimate
        self.normal = wp.zeros(res, dtype=float, device=dev)  # N s, z of the unmasked gradient
        self.region = wp.zeros(res, dtype=int, device=dev)  # 1: the ground may hold the node
        self.H_new = wp.zeros(solver.num_particles, dtype=wp.mat33, device=dev)  # [P] F(u) - I
        self.all_nodes = wp.zeros(int(np.prod(res)), dtype=wp.vec3i, device=dev)
        self.nodes = self.all_nodes[:0]  # [n] the nodes of the last solve
        self.count = wp.zeros(1, dtype=int, device=dev)
        self.scalar = wp.zeros(1, dtype=wp.float64, device=dev)
        self.sums = wp.zeros(3, dtype=wp.float64, device=dev)
        self.total_mass = 0.0  # kg on the step's nodes
        self.log: list[SolveStats] = []
        self._counts = [0, 0]  # products, gradients of the current sub-step

    # ------------------------------------------------------------------ passes
    def _grid_args(self, solver: MPMSolver, h: float) -> list:
        g = solver.grid
        return [wp.vec3(*g.origin), g.dx, h, wp.vec3i(*g.res)]

    def _gradient(self, solver: MPMSolver, h: float, nodes: wp.array) -> tuple[float, float]:
        """Gradient at ``u`` into ``grad``, ``H_new`` at ``u``; returns (energy J, RMS residual m/s)."""
        ps, dev = solver.particles, solver.device
        self._counts[1] += 1
        wp.launch(LA.zero_nodes, len(nodes), [nodes, self.grad], device=dev)
        self.scalar.zero_()
        self.sums.zero_()
        wp.launch(
            IK.gradient_pass,
            solver.num_particles,
            [self.u, ps.x, ps.H, ps.vol0, ps.mat_table, ps.material, *self._grid_args(solver, h)]
            + [self.H_new, self.grad, self.scalar],
            device=dev,
        )
        wp.launch(
            IK.finish_gradient,
            len(nodes),
            [nodes, self.u, self.target, self.mass, self.free, self.grad, self.sums, self.normal],
            device=dev,
        )
        s = self.sums.numpy()
        self.total_mass = float(s[2])
        return float(self.scalar.numpy()[0] + s[0]), math.sqrt(max(float(s[1]), 0.0) / self.total_mass)

    def _hessian(self, solver: MPMSolver, h: float, nodes: wp.array, d: wp.array) -> float:
        """q = (d^2 E / du^2) d on the free components; returns d . q."""
        ps, dev = solver.particles, solver.device
        self._counts[0] += 1
        wp.launch(LA.zero_nodes, len(nodes), [nodes, self.q], device=dev)
        wp.launch(
            IK.hessian_pass,
            solver.num_particles,
            [d, ps.x, ps.H, self.H_new, ps.vol0, ps.mat_table, ps.material, *self._grid_args(solver, h)]
            + [self.q],
            device=dev,
        )
        self.scalar.zero_()
        wp.launch(
            IK.finish_hessian, len(nodes), [nodes, d, self.mass, self.free, self.q, self.scalar], device=dev
        )
        return float(self.scalar.numpy()[0])

    def _dot(self, nodes: wp.array, a: wp.array, b: wp.array, dev) -> float:
        self.scalar.zero_()
        wp.launch(LA.dot_nodes, len(nodes), [nodes, a, b, self.scalar], device=dev)
        return float(self.scalar.numpy()[0])

    def _conjugate_gradient(self, solver: MPMSolver, h: float, nodes: wp.array, rr0: float) -> None:
        """Newton direction ``d`` ~ -H^-1 grad (CG from 0, Jacobi preconditioner m + diag).

        Stops at negative curvature with what it has (the preconditioned gradient if nothing), or
        when the mass-weighted residual fell to ``cg_tolerance`` of the gradient's.
        """
        dev, n = solver.device, len(nodes)
        self.scalar.zero_()
        wp.launch(
            LA.cg_start,
            n,
            [nodes, self.grad, self.mass, self.diag, self.r, self.z, self.p, self.d, self.scalar],
            device=dev,
        )
        rz = float(self.scalar.numpy()[0])
        stop = (self.settings.cg_tolerance**2) * rr0
        for k in range(self.settings.max_cg):
            pq = self._hessian(solver, h, nodes, self.p)
            if pq <= 0.0:
                if k == 0:
                    wp.copy(self.d, self.p)
                return
            self.sums.zero_()
            wp.launch(
                LA.cg_update,
                n,
                [nodes, rz / pq, self.p, self.q, self.mass, self.diag, self.d, self.r, self.z, self.sums],
                device=dev,
            )
            s = self.sums.numpy()
            if float(s[1]) <= stop:
                return
            wp.launch(LA.cg_direction, n, [nodes, float(s[0]) / rz, self.z, self.p], device=dev)
            rz = float(s[0])

    def _newton(self, solver: MPMSolver, h: float, nodes: wp.array, tol: float, budget: int):
        """Newton iterations from ``u`` until the residual is below ``tol`` or ``budget`` is spent;
        returns (iterations, residual m/s, converged)."""
        dev, n, cfg = solver.device, len(nodes), self.settings
        energy, res = self._gradient(solver, h, nodes)
        for it in range(budget):
            if res <= tol:
                return it, res, True
            self._conjugate_gradient(solver, h, nodes, res * res * self.total_mass)
            slope = self._dot(nodes, self.grad, self.d, dev)
            if slope >= 0.0:  # not a descent direction (an indefinite Hessian): precondition -grad
                wp.launch(
                    LA.cg_start,
                    n,
                    [nodes, self.grad, self.mass, self.diag, self.r, self.z, self.d, self.q, self.scalar],
                    device=dev,
                )
                slope = self._dot(nodes, self.grad, self.d, dev)
            wp.copy(self.u0, self.u)
            alpha = 1.0
            for _ in range(cfg.max_halvings):
                wp.launch(LA.axpy_nodes, n, [nodes, alpha, self.d, self.u0, self.u], device=dev)
                e_new, res_new = self._gradient(solver, h, nodes)
                # float32 particle energies sum to about 1e-7 relative: smaller changes are noise.
                if e_new <= energy + 1.0e-4 * alpha * slope + 1.0e-6 * abs(energy):
                    break
                alpha *= 0.5
            else:  # no decrease along d: the iterate is as good as float32 gets
                wp.copy(self.u, self.u0)
                energy, res = self._gradient(solver, h, nodes)
                return it + 1, res, res <= tol
            energy, res = e_new, res_new
        return budget, res, res <= tol

    # ------------------------------------------------------------------ the hook
    def apply(self, solver: MPMSolver, dt: float) -> None:
        dev, g, scene, cfg = solver.device, solver.grid, solver.scene, self.settings
        lo, hi = solver.active_box
        self.count.zero_()
        wp.launch(
            IK.collect_nodes,
            tuple(int(b - a) + 1 for a, b in zip(lo, hi, strict=True)),
            [solver.grid_v, solver.arrays.touched, solver.launches.next_stamp, wp.vec3i(*lo)]
            + [self.all_nodes, self.count],
            device=dev,
        )
        n = int(self.count.numpy()[0])
        if n == 0:
            return
        nodes = self.nodes = self.all_nodes[:n]
        h = self.theta * dt
        ground = scene.ground.pack() if scene.ground is not None else no_ground()
        origin = wp.vec3(*g.origin)
        wp.launch(
            IK.init_nodes,
            n,
            [
                nodes,
                solver.grid_v,
                wp.vec3i(*g.res),
                origin,
                g.dx,
                h,
                wp.vec3(*scene.gravity),
                math.exp(-scene.damping * h),
            ]
            + [ground, solver.config.boundary_cells, self.v_transfer, self.target, self.u, self.free]
            + [self.mass, self.diag, self.grad, self.region],
            device=dev,
        )
        ps = solver.particles
        wp.launch(
            IK.preconditioner_pass,
            solver.num_particles,
            [ps.x, ps.H, ps.vol0, ps.mat_table, ps.material, *self._grid_args(solver, h), self.diag],
            device=dev,
        )
        self._counts = [0, 0]
        first = self._gradient(solver, h, nodes)[1]
        tol = max(cfg.tolerance, cfg.relative_tolerance * first)
        newton, changes, converged, res = 0, 0, False, first
        for _ in range(cfg.max_contact_rounds + 1):
            its, res, converged = self._newton(solver, h, nodes, tol, cfg.max_newton - newton)
            newton += its
            self.count.zero_()
            wp.launch(
                IK.update_contacts,
                n,
                [nodes, self.region, self.normal, origin, g.dx, ground, self.u, self.free, self.count],
                device=dev,
            )
            changed = int(self.count.numpy()[0])
            changes += changed
            if not changed or newton >= cfg.max_newton:
                break
        products, gradients = self._counts
        self.log.append(
            SolveStats(solver.time, dt, n, newton, products, gradients, changes, res, first, converged)
        )
        wp.launch(
            IK.write_velocities,
            n,
            [nodes, self.u, self.v_transfer, self.free, self.theta, solver.grid_v],
            device=dev,
        )
