"""Verification through the planner: an elastic cube at the planner's defaults against statics.

The cases of ``analytic.py`` build particle lattices by hand; these start from Gaussians,
as the pipeline does, so they also check the planner's particle sampling (sampling.py).

Static sag of a block under its own weight (height H, density rho, gravity g). At depth s below
the top the vertical stress is rho g s; with a modulus E' relating vertical stress and strain the
column shortens by

    delta = integral_0^H rho g s / E' ds = rho g H^2 / (2 E')

* frictionless floor ("slip"): nothing holds the block's sides or base, the stress is uniaxial
  and E' = E (Young's modulus). This is the exact linear-elastic solution of a prism on a
  frictionless base (Timoshenko and Goodier, Theory of Elasticity, the bar under its own weight).
* sticky floor: the base cannot widen. Where the block is laterally confined the modulus is the
  constrained (P-wave) modulus M = E (1 - nu) / ((1 + nu)(1 - 2 nu)); far from the base the
  block is free again (E). A cube is neither, so its sag lies between rho g H^2 / (2 M) and
  rho g H^2 / (2 E); the test accepts that interval, widened by the tolerance.
* Coulomb friction (the drop scene's mu = 0.3) holds the base partly: the same interval.

The measured height is that of the Gaussians (mean top face minus mean bottom face), averaged
over the last ``window`` seconds: MPM damps an elastic body's wobble only slowly.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from physgm.cameras import Cameras, orbit_cameras
from physgm.gaussians import Gaussians
from physgm.sim.constitutive import MaterialParams
from physgm.sim.gaussian_trajectory import GaussianTrajectory, simulate
from physgm.sim.mpm.boundary import GroundPlane
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.stepping import SolverConfig
from physgm.sim.planner import PlannerConfig

G = 9.81


def static_sag(
    density: float, height: float, E: float, nu: float, floor: str, gravity: float = G
) -> tuple[float, float]:
    """(smallest, largest) static sag rho g H^2 / (2 E') of a block on a floor, m (module docstring).

    ``floor``: "slip" (E' = E, one value) or "sticky" / "friction" (E' between E and the
    constrained modulus M).
    """
    free = density * gravity * height**2 / (2.0 * E)
    if floor == "slip":
        return free, free
    if floor not in ("sticky", "friction"):
        raise ValueError(f"floor must be slip, sticky or friction, got {floor!r}")
    constrained = E * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return density * gravity * height**2 / (2.0 * constrained), free


def cube_gaussians(side: float, n: int = 20_000, seed: int = 0) -> Gaussians:
    """n small Gaussians on the surface of a cube resting on z = 0 (a 3DGS-like hollow shell)."""
    g = torch.Generator().manual_seed(seed)
    face = torch.randint(0, 6, (n,), generator=g)
    pts = (torch.rand(n, 3, generator=g) - 0.5) * side
    pts[torch.arange(n), face // 2] = side * ((face % 2).float() - 0.5)
    pts[:, 2] += side / 2
    return Gaussians(
        means=pts,
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        scales=torch.full((n, 3), side / 200),
        opacities=torch.full((n,), 0.9),
        colors=torch.rand(n, 3, generator=g),
    )


def _camera(side: float) -> Cameras:
    return orbit_cameras(
        [30.0], [15.0], radius=8 * side, fov_deg=40.0, width=256, height=256, target=(0.0, 0.0, side)
    )


def cube_heights(traj: GaussianTrajectory, side: float) -> np.ndarray:
    """[T] height of the Gaussian cube per frame: mean top face minus mean bottom face, m."""
    rest = traj.gaussians.means[:, 2] - traj.gaussians.means[:, 2].min()
    top, bottom = rest > side - 1e-4, rest < 1e-4
    z = traj.means()[:, :, 2]  # [T, N]
    return (z[:, top].mean(1) - z[:, bottom].mean(1)).double().numpy()


def elastic_cube(
    floor: str = "slip",  # slip | friction (Coulomb mu = 0.3, as the drop scene) | sticky
    drop: float = 0.0,  # m, gap under the cube at t = 0
    side: float = 0.2,  # m
    E: float = 1e4,  # Pa (jelly's table value)
    nu: float = 0.45,
    density: float = 1000.0,
    seconds: float = 2.0,
    window: float = 0.4,  # s averaged at the end
    tolerance: float = 0.05,  # relative to the static-sag height H - delta
    planner: PlannerConfig | None = None,
) -> dict:
    """A jelly cube at the planner's defaults settles to its static-sag height (module docstring)."""
    gaussians = cube_gaussians(side)
    gaussians.means[:, 2] += drop
    mode, friction = {"slip": ("slip", 0.0), "friction": ("separate", 0.3), "sticky": ("sticky", 0.0)}[floor]
    scene = Scene(ground=GroundPlane(0.0, friction=friction, mode=mode))
    material = MaterialParams("fixed_corotated", E, nu, density)
    frame_dt = 0.04
    n_frames = int(round(seconds / frame_dt)) + 1
    # No early stop: the averaging window must see the wobble, not a held frame.
    cfg = planner or PlannerConfig(rest_frames=10**6)
    solver = SolverConfig(frame_dt=frame_dt)
    traj = simulate(gaussians, material, scene, _camera(side), n_frames=n_frames, planner=cfg, solver=solver)
    h = cube_heights(traj, side)
    last = max(1, int(round(window / frame_dt)))
    settled = float(h[-last:].mean())
    lo, hi = static_sag(density, side, E, nu, floor)
    target_lo, target_hi = side - hi, side - lo  # static heights, m
    error = max(target_lo - settled, settled - target_hi, 0.0) / target_lo
    # Rebound: the highest the cube stretches back after its first squash (first local minimum).
    first = int(np.argmax(h < side - 1e-3)) if (h < side - 1e-3).any() else len(h) - 1
    while first + 1 < len(h) and h[first + 1] <= h[first]:
        first += 1
    rebound = float(h[first + 1 :].max()) if first + 1 < len(h) else math.nan
    name = f"elastic_cube_{floor}" + (f"_drop{drop:g}m" if drop > 0 else "")
    return {
        "name": name,
        "error": error,
        "tolerance": tolerance,
        "passed": bool(error <= tolerance and math.isfinite(settled)),
        "height_m": settled,
        "static_height_m": [target_lo, target_hi],
        "min_height_m": float(h.min()),
        "rebound_height_m": rebound,
        "heights_m": h.round(5).tolist(),
        "particles": len(traj.particles),
        "particles_per_cell": float(len(traj.particles) * traj.plan.dx**3 / side**3),
        "grid_cells": traj.plan.summary()["grid_cells"],
        "substeps": traj.substeps,
        "seconds": traj.seconds,
    }
