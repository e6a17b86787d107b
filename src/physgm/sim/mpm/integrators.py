"""The integrator registry: ``SolverConfig.integrator`` -> the solver class that runs it."""

from __future__ import annotations

from collections.abc import Sequence

import warp as wp

from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.implicit import ImplicitMPMSolver
from physgm.sim.mpm.pressure import PressureSplitMPMSolver
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.solver import MPMSolver
from physgm.sim.mpm.state import Particles
from physgm.sim.mpm.stepping import SolverConfig

INTEGRATORS: dict[str, type[MPMSolver]] = {
    "explicit": MPMSolver,  # CFL-limited MLS-MPM, every material
    "implicit": ImplicitMPMSolver,  # Newton on the incremental potential, elastic models only
    "pressure": PressureSplitMPMSolver,  # lam's volume term implicit on the grid, elastic models only
}


def make_solver(
    particles: Particles,
    materials: Sequence[MaterialParams],
    grid: GridSpec,
    scene: Scene | None = None,
    config: SolverConfig | None = None,
    device: str | wp.Device | None = "cpu",
) -> MPMSolver:
    """The solver of ``config.integrator`` (``MPMSolver``'s arguments)."""
    config = config or SolverConfig()
    if config.integrator not in INTEGRATORS:
        raise ValueError(f"unknown integrator {config.integrator!r}; known: {', '.join(INTEGRATORS)}")
    return INTEGRATORS[config.integrator](particles, materials, grid, scene, config, device)
