"""Measurements of ground contact and drift (issue 24 items 3 and 6; docs/measurements_sim.md).

* ``hertz_contact``: an elastic sphere thrown at a rigid frictionless floor without gravity. Its
  mean velocity changes only while the ground pushes, so the contact lasts from the first to
  the last change of the mean velocity. Hertz (Johnson, Contact Mechanics, 11.4): the
  approach peaks at delta = (15 m v^2 / (16 E* sqrt(R)))^(2/5), E* = E / (1 - nu^2), and
  contact lasts 2.94 delta / v.
* ``drop_drift``: a box of Gaussians, mirror-symmetric in x and y, dropped flat through the
  planner (``gaussian_trajectory.simulate``); how far its particles' centre moves sideways
  after it lands.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from physgm.cameras import orbit_cameras
from physgm.gaussians import Gaussians
from physgm.sim.constitutive import MaterialParams
from physgm.sim.gaussian_trajectory import simulate
from physgm.sim.mpm.boundary import GroundPlane
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.solver import MPMSolver
from physgm.sim.mpm.state import Particles
from physgm.sim.mpm.stepping import SolverConfig
from physgm.sim.planner import PlannerConfig


def hertz_contact(
    cells: int = 10,  # grid cells per sphere radius
    E: float = 1e5,  # Pa
    nu: float = 0.3,
    density: float = 1000.0,  # kg/m^3
    speed: float = 1.0,  # m/s, towards the floor
    radius: float = 0.1,  # m
    gap_cells: float = 2.0,  # gap between sphere and floor at t = 0, cells
    frame_dt: float = 5e-4,  # s, sampling of the mean velocity
    tolerance: float = 0.005,  # change of the mean velocity that counts as contact, x speed
    contact: str | None = None,  # GroundPlane.contact (None: its default)
) -> dict:
    """Contact duration of an elastic sphere on a slip floor against Hertz (module docstring)."""
    dx = radius / cells
    sp = dx / 2
    centre = np.array([0.0, 0.0, radius + gap_cells * dx])
    p = Particles.lattice(
        tuple(centre - radius),
        tuple(centre + radius),
        sp,
        inside=lambda x: ((x - centre) ** 2).sum(1) < radius**2,
    )
    p.v = np.tile([0.0, 0.0, -speed], (len(p), 1))
    mass = float(p.volume.sum() * density)
    delta = (15 * mass * speed**2 / (16 * E / (1 - nu**2) * math.sqrt(radius))) ** 0.4
    t_hertz = 2.94 * delta / speed
    # Tall enough that the rebounding sphere never reaches the top face within the window.
    top = 2.0 * radius + gap_cells * dx + 3.5 * t_hertz * speed
    grid = GridSpec.fit((-1.3 * radius, -1.3 * radius, 0.0), (1.3 * radius, 1.3 * radius, top), dx)
    ground = GroundPlane(0.0, friction=0.0, mode="slip", contact=contact)
    scene = Scene(gravity=(0.0, 0.0, 0.0), ground=ground)
    solver = MPMSolver(
        p, [MaterialParams("fixed_corotated", E, nu, density)], grid, scene, SolverConfig(frame_dt=frame_dt)
    )
    t_touch = gap_cells * dx / speed  # the sphere's surface reaches the plane
    ts, vz = [0.0], [-speed]
    try:
        while solver.time < t_touch + 3.0 * t_hertz:
            solver.step_frame()
            ts.append(solver.time)
            vz.append(float(solver.state().v[:, 2].astype(np.float64).mean()))
    finally:
        solver.close()
    ts, vz = np.array(ts), np.array(vz)
    pushed = np.nonzero(np.abs(vz + speed) > tolerance * speed)[0]
    moving = np.nonzero(np.abs(vz - vz[-1]) > tolerance * speed)[0]
    if len(pushed) == 0 or moving[-1] + 1 >= len(ts):
        raise RuntimeError("the sphere did not touch the floor and leave it again within 3 Hertz times")
    start, stop = ts[pushed[0]], ts[moving[-1] + 1]
    return {
        "cells_per_radius": cells,
        "particles": len(p),
        "hertz_s": t_hertz,
        "contact_s": stop - start,
        "error": (stop - start) / t_hertz - 1.0,
        "start_after_touch_cells": (start - t_touch) * speed / dx,
        "restitution": float(vz[-1] / speed),
    }


def box_gaussians(size=(0.1, 0.09, 0.1), n: int = 12, drop: float = 0.05) -> Gaussians:
    """A lattice of n^3 Gaussians filling a box centred on x = y = 0, ``drop`` m above z = 0."""
    u = (torch.arange(n, dtype=torch.float32) + 0.5) / n - 0.5
    pts = torch.cartesian_prod(u, u, u) * torch.tensor(size, dtype=torch.float32)
    pts[:, 2] += size[2] / 2 + drop
    return Gaussians(
        means=pts,
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(len(pts), 1),
        scales=torch.full((len(pts), 3), min(size) / n / 2),
        opacities=torch.full((len(pts),), 0.9),
        colors=torch.full((len(pts), 3), 0.5),
    )


def drop_drift(
    size=(0.1, 0.09, 0.1),  # m
    cells_across: int = 8,
    seconds: float = 2.0,
    E: float = 1e4,  # Pa (jelly)
    friction: float = 0.3,
    contact: str | None = None,  # GroundPlane.contact (None: its default)
) -> dict:
    """Sideways drift of a symmetric jelly box dropped 5 cm flat, through the planner (module docstring)."""
    camera = orbit_cameras(
        [30.0], [15.0], radius=0.8, fov_deg=40.0, width=256, height=256, target=(0.0, 0.0, 0.05)
    )
    traj = simulate(
        box_gaussians(size),
        MaterialParams("fixed_corotated", E, 0.45, 1000.0),
        Scene(ground=GroundPlane(0.0, friction=friction, mode="separate", contact=contact)),
        camera,
        n_frames=int(round(seconds / 0.04)) + 1,
        planner=PlannerConfig(rest_frames=10**6, cells_across=cells_across),
        solver=SolverConfig(frame_dt=0.04),
    )
    x = traj.x.astype(np.float64)
    dx = traj.plan.dx
    landed = int(np.argmax(x[:, :, 2].min(1) < dx))
    drift = x[-1, :, :2].mean(0) - x[landed, :, :2].mean(0)
    centre = 0.5 * (x[0].min(0) + x[0].max(0))
    return {
        "dx": dx,
        "landed_frame": landed,
        "centre_in_cell": ((centre[:2] - traj.plan.grid_lo[:2]) / dx % 1.0).round(4).tolist(),
        "drift_mm": (drift * 1e3).round(4).tolist(),
        "drift_px": float(np.linalg.norm(drift) * traj.plan.px_per_m),
        "lowest_particle_end_cells": float(x[-1, :, 2].min() / dx),
    }
