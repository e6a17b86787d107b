"""Implicit elastic MPM: sub-steps far above the explicit CFL limit for elastic materials.

The sub-step is the explicit one (``launches``: scatter, grid_update, g2p) with the stress
taken out of the scatter and the grid velocities replaced, between grid_update and g2p, by the
minimiser of an incremental potential (Gast et al. 2015, optimisation-based backward Euler):

    u = argmin  sum_i m_i |u_i - u*_i|^2 / 2 + sum_p V0_p psi(F_p(u)),
        F_p(u) = (I + h C_p(u)) F_p^n,  u*_i = v_i^n + h g,  h = theta dt,

found by Newton's method with a Jacobi-preconditioned conjugate gradient on the Hessian
(Hessian-vector products as in ``implicit_kernels``) and a backtracking line search on the
energy (``implicit_newton``). The ground acts on the predictor as in the explicit grid_update: a
node it holds keeps the ground's velocity for the step (normal stopped, Coulomb friction on the
tangent); after a solve, held nodes the body would lift are released and free nodes pushed into
the ground are held, and Newton continues (an active set). Particles then move and deform with u
over the whole step dt, and take the velocity change of v^{n+1} = v^n + (u - v^n) / theta: theta
= 1 is backward Euler (stable at any dt, damps what the step cannot resolve), theta = 1/2 the
implicit midpoint rule (keeps the energy of linear elasticity). Only elastic models whose stress
is the gradient of their ``energy`` take part (``IMPLICIT_MODELS``); plastic, granular and fluid
materials stay explicit.

The sub-step is ``SolverConfig.implicit_dt`` while the body is slow, and the advective limit
cfl dx / |v|max (particles cross at most ``cfl`` cells a step) when it is fast.

On this project's bench drops (docs/measurements_sim.md, section 10) it is an option, not a
default: every setting measured missed the 0.5 px bound (backward Euler takes the rebound, the
midpoint rule drifts in phase) and, but for one, took longer than the explicit step.
"""

from __future__ import annotations

from collections.abc import Sequence

import warp as wp

from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm import implicit_kernels as IK
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.implicit_newton import ImplicitStep, NewtonSettings
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.solver import MPMSolver
from physgm.sim.mpm.state import Particles
from physgm.sim.mpm.stepping import SolverConfig, implicit_step_speed
from physgm.warp_runtime import ensure_loaded

# Models whose stress is the gradient of their ``energy`` with no return mapping and no reset of
# F: the incremental potential exists for them. The others change F outside the energy.
IMPLICIT_MODELS = ("fixed_corotated", "neo_hookean")
# Passes over the particles (Hessian-vector products and gradients, each about an explicit sub-step's
# cost) one implicit sub-step takes at the fewest: 9 on a thrown 8 cm jelly block at 2 ms steps, 41-64
# on a resting one at 10 ms, up to 251 through an impact (the blocks of tests/sim/mpm/test_implicit.py,
# docs/measurements_sim.md section 37). A plan's cost counts sub-steps; an implicit one costs this many.
IMPLICIT_PASSES_MIN = 9


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


class ImplicitMPMSolver(MPMSolver):
    """``MPMSolver`` with the implicit elastic step (module docstring); same arguments.

    ``config.implicit_dt`` is the sub-step while the body is slow, ``config.implicit_theta`` the
    theta of the theta method; ``settings`` the Newton tolerances. A solve that ends unconverged
    still gives the particles its velocities and does not fail the frame (retrying such frames
    cost 2.2x and changed nothing visible: docs/measurements_sim.md section 10). ``implicit.log``
    holds one ``SolveStats`` per sub-step (``converged`` says which solves met the tolerance), the
    divergence guard's retried attempts included. Grid hooks added to ``hooks`` run after the
    solve and override it where they act. The ground and face impulses the observers see are
    those of the predictor, and a ground held at depth gets no friction on its surface node layer
    (``surface_friction`` acts on the predictor, which the solve replaces).
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
        scene = (scene or Scene()).with_ground_on_nodes()  # the solve drops the scatter's contact forces
        check_implicit(materials, scene)
        super().__init__(particles, materials, grid, scene, config, device)
        self.implicit = ImplicitStep(self, self.config.implicit_theta, settings or NewtonSettings())
        self.hooks.append(self.implicit)
        ensure_loaded(IK.clear_stress_channels, self.device)
        # The sub-step is implicit_dt for a slow body and the advective limit for a fast one.
        self._c_max = implicit_step_speed(self.config.cfl, self.grid.dx, self.config.implicit_dt)
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
