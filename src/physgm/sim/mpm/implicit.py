"""Implicit elastic MPM: sub-steps far above the explicit CFL limit for elastic materials.

The sub-step is the explicit one (``launches``: scatter, grid_update, g2p) with the stress
taken out of the scatter and the grid velocities replaced, between grid_update and g2p, by the
minimiser of an incremental potential (Gast et al. 2015, optimisation-based backward Euler):

    u = argmin  sum_i m_i |u_i - u*_i|^2 / 2 + sum_p V0_p psi(F_p(u)),
        F_p(u) = (I + h C_p(u)) F_p^n,  u*_i = v_i^n + h g,  h = theta dt,

found by Newton's method with a Jacobi-preconditioned conjugate gradient on the Hessian
(Hessian-vector products as in ``implicit_kernels``) and a backtracking line search on the
energy. The ground acts on the predictor as in the explicit grid_update: a node it holds keeps
the ground's velocity for the step (normal stopped, Coulomb friction on the tangent). Particles
then move and deform with u over the whole step dt, and take the velocity change of
v^{n+1} = v^n + (u - v^n) / theta: theta = 1 is backward Euler (stable at any dt, damps what the
step cannot resolve), theta = 1/2 the implicit midpoint rule (keeps the energy of linear
elasticity). Only elastic models whose stress is the gradient of their ``energy`` take part
(``IMPLICIT_MODELS``); plastic, granular and fluid materials stay explicit.

The sub-step is ``SolverConfig.implicit_dt`` while the body is slow, and the advective limit
cfl dx / |v|max (particles cross at most ``cfl`` cells a step) when it is fast.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm import implicit_kernels as IK
from physgm.sim.mpm.boundary import no_ground
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.solver import MPMSolver
from physgm.sim.mpm.state import Particles
from physgm.sim.mpm.stepping import SolverConfig
from physgm.warp_runtime import ensure_loaded

# Models whose stress is the gradient of their ``energy`` with no return mapping and no reset of
# F: the incremental potential exists for them. The others change F outside the energy.
IMPLICIT_MODELS = ("fixed_corotated", "neo_hookean")


@dataclass(frozen=True)
class NewtonSettings:
    """Convergence settings of the per-step minimisation."""

    tolerance: float = 1.0e-3  # m/s, mass-weighted RMS of the residual m^-1 dE/du that ends Newton
    relative_tolerance: float = 1.0e-5  # or this fraction of the step's first residual
    max_newton: int = 12  # Newton iterations per sub-step
    max_cg: int = 400  # CG iterations per Newton iteration
    cg_tolerance: float = 1.0e-2  # CG stops at this fraction of the Newton residual's norm
    max_halvings: int = 12  # line-search step halvings before the iteration gives up
    coarse: bool = True  # add the exact inverse on the 12 affine velocity fields to Jacobi


@dataclass(frozen=True)
class SolveStats:
    """One sub-step's minimisation."""

    time: float  # s, at the start of the sub-step
    dt: float  # s
    nodes: int  # grid nodes in the solve
    newton: int  # Newton iterations
    cg: int  # CG iterations, all Newton iterations together
    products: int  # Hessian-vector products (CG and coarse space): each costs about one explicit sub-step
    residual: float  # m/s, final mass-weighted RMS residual
    first_residual: float  # m/s, at the predictor
    converged: bool  # the residual met a tolerance (else the iterations or the line search ran out)


def check_implicit(materials: Sequence[MaterialParams], scene: Scene) -> None:
    """Raise ValueError for what the implicit step does not handle, saying what to do instead."""
    unsupported = sorted({m.model for m in materials} - set(IMPLICIT_MODELS))
    if unsupported:
        raise ValueError(
            f"the implicit integrator handles the elastic models {', '.join(IMPLICIT_MODELS)} only, "
            f"not {', '.join(unsupported)} (their return mapping changes F outside the energy); "
            "run them with integrator='explicit'"
        )
    extras = {
        "velocity boxes": bool(scene.boxes),
        "side walls": bool(scene.walls),
        "periodic axes": bool(scene.periodic),
    }
    named = [name for name, present in extras.items() if present]
    if named:
        raise ValueError(
            f"the implicit integrator supports gravity and a ground plane only, not {', '.join(named)}; "
            "run this scene with integrator='explicit'"
        )


class ImplicitStep:
    """The grid hook that replaces grid_update's velocities by the minimiser (module docstring).

    Dense [nx, ny, nz] work arrays are allocated once; every pass runs over the nodes that hold
    mass this sub-step (``nodes[:count]``) and the particles.
    """

    def __init__(self, solver: MPMSolver, theta: float, settings: NewtonSettings) -> None:
        self.theta, self.settings = theta, settings
        dev, res = solver.device, solver.grid.res
        ensure_loaded(IK.gradient_pass, dev)
        vec = {name: wp.zeros(res, dtype=wp.vec3, device=dev) for name in _VEC_FIELDS}
        self.u, self.u0, self.target, self.v_transfer, self.free = (vec[n] for n in _VEC_FIELDS[:5])
        self.grad, self.d, self.r, self.z, self.p, self.q = (vec[n] for n in _VEC_FIELDS[5:])
        self.mass = wp.zeros(res, dtype=float, device=dev)
        self.diag = wp.zeros(res, dtype=float, device=dev)
        self.H_new = wp.zeros(solver.num_particles, dtype=wp.mat33, device=dev)
        self.all_nodes = wp.zeros(int(np.prod(res)), dtype=wp.vec3i, device=dev)
        self.count = wp.zeros(1, dtype=int, device=dev)
        self.nodes = self.all_nodes[:0]  # [n] the nodes of the last solve
        self.energy = wp.zeros(1, dtype=wp.float64, device=dev)
        self.sums = wp.zeros(3, dtype=wp.float64, device=dev)
        self.total_mass = 0.0  # kg on the step's nodes
        self.coarse_sums = wp.zeros(IK.COARSE, dtype=wp.float64, device=dev)
        self.coarse_y = wp.zeros(IK.COARSE, dtype=float, device=dev)
        self.coarse_inv = np.zeros((IK.COARSE, IK.COARSE))
        self._frame = (wp.vec3(0.0), 1.0)  # centre and scale of the coarse space's coordinates
        self.log: list[SolveStats] = []

    # ------------------------------------------------------------------ passes
    def _gradient(self, solver: MPMSolver, h: float, nodes: wp.array) -> tuple[float, float]:
        """Gradient at ``u`` into ``grad``, ``H_new`` at ``u``; returns (energy J, RMS residual m/s)."""
        ps, g, dev = solver.particles, solver.grid, solver.device
        wp.launch(IK.zero_nodes, len(nodes), [nodes, self.grad], device=dev)
        self.energy.zero_()
        self.sums.zero_()
        wp.launch(
            IK.gradient_pass,
            solver.num_particles,
            [
                self.u,
                ps.x,
                ps.H,
                ps.vol0,
                ps.mat_table,
                ps.material,
                wp.vec3(*g.origin),
                g.dx,
                h,
                wp.vec3i(*g.res),
                self.H_new,
                self.grad,
                self.energy,
            ],
            device=dev,
        )
        wp.launch(
            IK.finish_gradient,
            len(nodes),
            [nodes, self.u, self.target, self.mass, self.free, self.grad, self.sums],
            device=dev,
        )
        s = self.sums.numpy()
        self.total_mass = float(s[2])
        return float(self.energy.numpy()[0] + s[0]), math.sqrt(max(float(s[1]), 0.0) / self.total_mass)

    def _hessian(self, solver: MPMSolver, h: float, nodes: wp.array, d: wp.array) -> float:
        """q = (d^2 E / du^2) d on the free components; returns d . q."""
        ps, g, dev = solver.particles, solver.grid, solver.device
        wp.launch(IK.zero_nodes, len(nodes), [nodes, self.q], device=dev)
        wp.launch(
            IK.hessian_pass,
            solver.num_particles,
            [
                d,
                ps.x,
                ps.H,
                self.H_new,
                ps.vol0,
                ps.mat_table,
                ps.material,
                wp.vec3(*g.origin),
                g.dx,
                h,
                wp.vec3i(*g.res),
                self.q,
            ],
            device=dev,
        )
        self.energy.zero_()
        wp.launch(
            IK.finish_hessian, len(nodes), [nodes, d, self.mass, self.free, self.q, self.energy], device=dev
        )
        return float(self.energy.numpy()[0])

    def _coarse_setup(self, solver: MPMSolver, h: float, nodes: wp.array) -> None:
        """The 12 x 12 Hessian of the affine velocity fields at the current iterate (12 products)."""
        dev = solver.device
        A = np.zeros((IK.COARSE, IK.COARSE))
        for k in range(IK.COARSE):
            self.coarse_y.assign(np.eye(IK.COARSE, dtype=np.float32)[k])
            wp.launch(
                IK.coarse_prolong,
                len(nodes),
                [nodes, self.coarse_y, self.free, *self._frame, 0, self.p],
                device=dev,
            )
            self._hessian(solver, h, nodes, self.p)
            A[:, k] = self._restrict(nodes, self.q, dev)
        self.coarse_inv = np.linalg.pinv(0.5 * (A + A.T), rcond=1e-7, hermitian=True)

    def _restrict(self, nodes: wp.array, r: wp.array, dev) -> np.ndarray:
        self.coarse_sums.zero_()
        wp.launch(
            IK.coarse_restrict, len(nodes), [nodes, r, self.free, *self._frame, self.coarse_sums], device=dev
        )
        return self.coarse_sums.numpy()

    def _precondition(self, nodes: wp.array, dev) -> float:
        """z (Jacobi, set by the CG kernels) += Z A_c^-1 Z^T r; returns r . z."""
        if not self.settings.coarse:
            return self._dot(nodes, self.r, self.z, dev)
        self.coarse_y.assign((self.coarse_inv @ self._restrict(nodes, self.r, dev)).astype(np.float32))
        wp.launch(
            IK.coarse_prolong,
            len(nodes),
            [nodes, self.coarse_y, self.free, *self._frame, 1, self.z],
            device=dev,
        )
        return self._dot(nodes, self.r, self.z, dev)

    def _conjugate_gradient(self, solver: MPMSolver, h: float, nodes: wp.array, rr0: float) -> int:
        """Newton direction ``d`` ~ -H^-1 grad; returns the CG iterations taken.

        Preconditioner: Jacobi plus the exact inverse on the affine velocity fields (additive
        two-level). Jacobi alone leaves the body's slow modes (translation, rotation, uniform
        strain) against the stiff ones: a large step's Hessian m + h^2 K spans (c h / dx)^2.
        """
        dev, n = solver.device, len(nodes)
        if self.settings.coarse:
            self._coarse_setup(solver, h, nodes)
        self.energy.zero_()
        wp.launch(
            IK.cg_start,
            n,
            [nodes, self.grad, self.mass, self.diag, self.r, self.z, self.p, self.d, self.energy],
            device=dev,
        )
        rz = self._precondition(nodes, dev)
        wp.copy(self.p, self.z)
        stop = (self.settings.cg_tolerance**2) * rr0
        for k in range(self.settings.max_cg):
            pq = self._hessian(solver, h, nodes, self.p)
            if pq <= 0.0:  # negative curvature: keep what CG has, or the preconditioned gradient
                if k == 0:
                    wp.copy(self.d, self.p)
                return k + 1
            alpha = rz / pq
            self.sums.zero_()
            wp.launch(
                IK.cg_update,
                n,
                [nodes, alpha, self.p, self.q, self.mass, self.diag, self.d, self.r, self.z, self.sums],
                device=dev,
            )
            rr = float(self.sums.numpy()[1])
            if rr <= stop:
                return k + 1
            rz_new = self._precondition(nodes, dev)
            wp.launch(IK.cg_direction, n, [nodes, rz_new / rz, self.z, self.p], device=dev)
            rz = rz_new
        return self.settings.max_cg

    def _dot(self, nodes: wp.array, a: wp.array, b: wp.array, dev) -> float:
        self.energy.zero_()
        wp.launch(IK.dot_nodes, len(nodes), [nodes, a, b, self.energy], device=dev)
        return float(self.energy.numpy()[0])

    # ------------------------------------------------------------------ the hook
    def apply(self, solver: MPMSolver, dt: float) -> None:
        dev, g, scene, cfg = solver.device, solver.grid, solver.scene, self.settings
        lo, hi = solver.active_box
        self.count.zero_()
        wp.launch(
            IK.collect_nodes,
            tuple(int(b - a) + 1 for a, b in zip(lo, hi, strict=True)),
            [
                solver.grid_v,
                solver.arrays.touched,
                solver.launches.stamp,
                wp.vec3i(*lo),
                self.all_nodes,
                self.count,
            ],
            device=dev,
        )
        n = int(self.count.numpy()[0])
        if n == 0:
            return
        nodes = self.nodes = self.all_nodes[:n]
        h = self.theta * dt
        lo_, hi_ = np.asarray(lo, float), np.asarray(hi, float)
        self._frame = (wp.vec3(*(0.5 * (lo_ + hi_))), 2.0 / float(max(np.max(hi_ - lo_), 1.0)))
        ground = scene.ground.pack() if scene.ground is not None else no_ground()
        wp.launch(
            IK.init_nodes,
            n,
            [
                nodes,
                solver.grid_v,
                wp.vec3(*g.origin),
                g.dx,
                h,
                wp.vec3(*scene.gravity),
                math.exp(-scene.damping * h),
                ground,
                solver.config.boundary_cells,
                self.v_transfer,
                self.target,
                self.u,
                self.free,
                self.mass,
                self.diag,
                self.grad,
            ],
            device=dev,
        )
        ps = solver.particles
        wp.launch(
            IK.preconditioner_pass,
            solver.num_particles,
            [
                ps.x,
                ps.H,
                ps.vol0,
                ps.mat_table,
                ps.material,
                wp.vec3(*g.origin),
                g.dx,
                h,
                wp.vec3i(*g.res),
                self.diag,
            ],
            device=dev,
        )
        energy, res = self._gradient(solver, h, nodes)
        first, newton, cg, converged = res, 0, 0, False
        while newton < cfg.max_newton:
            if res <= max(cfg.tolerance, cfg.relative_tolerance * first):
                converged = True
                break
            newton += 1
            cg += self._conjugate_gradient(solver, h, nodes, res * res * self.total_mass)
            slope = self._dot(nodes, self.grad, self.d, dev)
            if slope >= 0.0:  # not a descent direction (an indefinite Hessian): precondition -grad
                wp.launch(
                    IK.cg_start,
                    n,
                    [nodes, self.grad, self.mass, self.diag, self.r, self.z, self.d, self.q, self.energy],
                    device=dev,
                )
                slope = self._dot(nodes, self.grad, self.d, dev)
            wp.copy(self.u0, self.u)
            alpha, accepted = 1.0, False
            for _ in range(cfg.max_halvings):
                wp.launch(IK.axpy_nodes, n, [nodes, alpha, self.d, self.u0, self.u], device=dev)
                e_new, res_new = self._gradient(solver, h, nodes)
                # float32 particle energies sum to about 1e-7 relative: smaller changes are noise.
                if e_new <= energy + 1.0e-4 * alpha * slope + 1.0e-6 * abs(energy):
                    accepted = True
                    break
                alpha *= 0.5
            if not accepted:  # the line search found no decrease: the iterate is as good as float32 gets
                wp.copy(self.u, self.u0)
                energy, res = self._gradient(solver, h, nodes)
                break
            energy, res = e_new, res_new
        else:
            converged = res <= max(cfg.tolerance, cfg.relative_tolerance * first)
        products = cg + (IK.COARSE * newton if cfg.coarse else 0)
        self.log.append(SolveStats(solver.time, dt, n, newton, cg, products, res, first, converged))
        wp.launch(
            IK.write_velocities,
            n,
            [nodes, self.u, self.v_transfer, self.free, self.theta, solver.grid_v],
            device=dev,
        )


_VEC_FIELDS = ("u", "u0", "target", "v_transfer", "free", "grad", "d", "r", "z", "p", "q")


class ImplicitMPMSolver(MPMSolver):
    """``MPMSolver`` with the implicit elastic step (module docstring); same arguments.

    ``config.implicit_dt`` is the sub-step while the body is slow, ``config.implicit_theta`` the
    theta of the theta method; ``settings`` the Newton tolerances. ``implicit.log`` holds one
    ``SolveStats`` per sub-step. Grid hooks added to ``hooks`` run after the solve and override it
    where they act. The ground and face impulses the observers see are those of the predictor.
    """

    def __init__(
        self,
        particles: Particles,
        materials: Sequence[MaterialParams],
        grid: GridSpec,
        scene: Scene | None = None,
        config: SolverConfig | None = None,
        device: str | wp.Device | None = "cpu",
        settings: NewtonSettings | None = None,
    ) -> None:
        check_implicit(materials, scene or Scene())
        super().__init__(particles, materials, grid, scene, config, device)
        self.implicit = ImplicitStep(self, self.config.implicit_theta, settings or NewtonSettings())
        self.hooks.append(self.implicit)
        ensure_loaded(IK.clear_stress_channels, self.device)
        # The CFL rule dt = cfl dx / (c + |v|max) with the speed c that gives implicit_dt at rest:
        # the sub-step is implicit_dt for a slow body and the advective limit for a fast one.
        self._c_max = self.config.cfl * self.grid.dx / self.config.implicit_dt
        self._fit_active(self.stable_dt())

    def substep(self, dt: float) -> None:
        if not self.launches.scattered:
            self.particles.stress.zero_()  # p2g then scatters no stress force
        else:  # g2p scattered its stress force for this sub-step: clear it
            lo, hi = self.active_box
            dims = tuple(int(b - a) + 1 for a, b in zip(lo, hi, strict=True))
            for acc in self.arrays.acc[: self.threads]:
                wp.launch(IK.clear_stress_channels, dims, [wp.vec3i(*lo), acc], device=self.device)
        super().substep(dt)
