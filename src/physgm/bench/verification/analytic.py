"""Verification cases of the MPM solver against analytic results (used by tests and the bench).

Each case builds a small scene, runs the solver and returns ``{"name", "error", "tolerance",
"passed", ...details}``; ``fast=True`` is the coarse version run by the default tests,
``fast=False`` the finer one of ``python -m physgm.bench sim-verify``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from physgm.bench.verification.granular import ASPECTS, FAST_CELLS, FULL_CELLS, column_collapse
from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm.boundary import GroundPlane, VelocityBox
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.solver import MPMSolver
from physgm.sim.mpm.state import Particles
from physgm.sim.mpm.stepping import SolverConfig

G = 9.81


def _result(name: str, error: float, tolerance: float, passed: bool | None = None, **details) -> dict:
    ok = bool(error <= tolerance) if passed is None else bool(passed)
    return {"name": name, "error": float(error), "tolerance": float(tolerance), "passed": ok, **details}


def _solver(particles, material, lo, hi, dx, scene, frame_dt=0.04, **cfg) -> MPMSolver:
    grid = GridSpec.fit(lo, hi, dx)
    return MPMSolver(particles, [material], grid, scene, SolverConfig(frame_dt=frame_dt, **cfg))


class _DtRecorder:
    """Grid hook that records every sub-step length."""

    def __init__(self) -> None:
        self.dts: list[float] = []

    def apply(self, solver, dt: float) -> None:
        self.dts.append(dt)


def free_fall(fast: bool = True) -> dict:
    """A block thrown upwards without ground follows symplectic Euler: v += g dt, x += v dt."""
    sp = 0.0125 if fast else 0.00625
    p = Particles.lattice((0.0, 0.0, 0.0), (0.1, 0.1, 0.1), sp)
    v0 = np.array([0.3, -0.2, 1.5])
    p.v = np.tile(v0, (len(p), 1))
    n_frames = 6 if fast else 25
    t_end = n_frames * 0.04
    # Box swept by the ballistic flight (apex and end point), plus the block itself.
    times = np.array([0.0, t_end, min(max(v0[2] / G, 0.0), t_end)])
    path = v0[None, :] * times[:, None] + 0.5 * np.array([0.0, 0.0, -G]) * times[:, None] ** 2
    lo, hi = path.min(0) - 0.05, path.max(0) + 0.15
    solver = _solver(p, MaterialParams("fixed_corotated", 1e5, 0.3, 1000.0), lo, hi, 2 * sp, Scene())
    rec = _DtRecorder()
    solver.hooks.append(rec)
    x0 = solver.state().x.astype(np.float64).mean(0)
    for _ in range(n_frames):
        solver.step_frame()
    x1 = solver.state().x.astype(np.float64).mean(0)
    x_ref, v = x0.copy(), v0.copy()
    for dt in rec.dts:
        v = v + np.array([0.0, 0.0, -G]) * dt
        x_ref = x_ref + v * dt
    err = np.linalg.norm((x1 - x0) - (x_ref - x0)) / np.linalg.norm(x_ref - x0)
    return _result("free_fall", err, 1e-5, substeps=len(rec.dts))


def resting_block(fast: bool = True) -> list[dict]:
    """A block on the ground settles: no penetration beyond a cell, no drift, energy never grows."""
    sp = 0.0125 if fast else 0.00625
    dx = 2 * sp
    p = Particles.lattice((-0.1, -0.1, 0.0), (0.1, 0.1, 0.1), sp)
    mat = MaterialParams("fixed_corotated", 2e5, 0.3, 1000.0)
    scene = Scene(ground=GroundPlane(0.0, friction=0.5, mode="separate"))
    solver = _solver(p, mat, (-0.15, -0.15, 0.0), (0.15, 0.15, 0.15), dx, scene)
    n_frames = 12 if fast else 50
    mass = float(p.volume.sum() * mat.density)
    e0 = solver.energy().total
    xy0 = solver.state().x[:, :2].astype(np.float64).mean(0)
    pen, drift, grow = 0.0, 0.0, -math.inf
    for _ in range(n_frames):
        solver.step_frame()
        x = solver.state().x.astype(np.float64)
        pen = max(pen, -float(x[:, 2].min()))
        drift = max(drift, float(np.linalg.norm(x[:, :2].mean(0) - xy0)))
        grow = max(grow, solver.energy().total - e0)
    scale = mass * G * 0.1
    return [
        _result("resting_block_penetration", pen / dx, 1.0, units="cells"),
        _result("resting_block_drift", drift / dx, 0.01, units="cells"),
        _result("resting_block_energy_growth", max(grow, 0.0) / scale, 1e-3, units="fraction of m g h"),
    ]


def bar_vibration(fast: bool = True) -> dict:
    """Axial vibration of a fixed-free bar (nu = 0): period 4 L / sqrt(E / rho)."""
    n_len = 32 if fast else 64
    length, rho, E = 1.0, 1000.0, 1.0e5
    dx = length / n_len
    sp = dx / 2
    w = 2 * dx
    p = Particles.lattice((0.0, 0.0, 0.0), (length, w, w), sp)
    c = math.sqrt(E / rho)
    amp = 0.01 * c  # peak velocity: strain amplitude ~1e-2
    p.v = np.zeros((len(p), 3))
    p.v[:, 0] = amp * np.sin(0.5 * math.pi * p.x[:, 0] / length)  # first mode shape
    clamp = VelocityBox((-1.0, -1.0, -1.0), (0.0, 1.0 + w, 1.0 + w))
    period = 4 * length / c
    frame_dt = period / 40
    solver = _solver(
        p,
        MaterialParams("fixed_corotated", E, 0.0, rho),
        (0, 0, 0),
        (1.2 * length, w, w),
        dx,
        Scene(gravity=(0.0, 0.0, 0.0), boxes=(clamp,)),
        frame_dt=frame_dt,
    )
    tip = p.x[:, 0] > length - dx
    times, disp = [0.0], [0.0]
    x_tip0 = float(p.x[tip, 0].mean())
    for _ in range(int(2.6 * 40)):
        solver.step_frame()
        times.append(solver.time)
        disp.append(float(solver.state().x[tip, 0].mean()) - x_tip0)
    return _result(
        "bar_vibration_period",
        abs(_period(np.array(times), np.array(disp)) / period - 1),
        0.02,
        expected_s=period,
    )


def _period(t: np.ndarray, y: np.ndarray) -> float:
    """Mean period from the upward zero crossings of ``y`` (linear interpolation)."""
    y = y - y.mean()
    s = np.sign(y)
    idx = np.nonzero((s[:-1] <= 0) & (s[1:] > 0))[0]
    if len(idx) < 2:
        idx = np.nonzero(s[:-1] * s[1:] < 0)[0]
        crossings = t[idx] - y[idx] * (t[idx + 1] - t[idx]) / (y[idx + 1] - y[idx])
        return float(2 * np.mean(np.diff(crossings))) if len(crossings) > 1 else math.nan
    crossings = t[idx] - y[idx] * (t[idx + 1] - t[idx]) / (y[idx + 1] - y[idx])
    return float(np.mean(np.diff(crossings)))


def cantilever(fast: bool = True) -> dict:
    """Clamped beam sagging under gravity (nu = 0, linear regime): static tip deflection.

    Reference: Timoshenko beam under the uniform load q = rho g b h, tip deflection
        q L^4 / (8 E I) + q L^2 / (2 kappa G A) = 3 rho g L^4 / (2 E h^2) (1 + (E / (3 kappa G)) (h / L)^2)
    with kappa = 5/6; the first factor is the Euler-Bernoulli value 3 rho g L^4 / (2 E h^2). A
    mass-proportional drag (critical for the fundamental mode, no effect on the static state)
    settles the beam; the deflection is the mean over the last period of the fundamental mode.
    """
    n_h = 3 if fast else 6
    slender = 6.0 if fast else 10.0
    h = 0.05
    length, dx, rho, nu = slender * h, h / n_h, 1000.0, 0.0
    E = 3 * rho * G * length**4 / (2 * 0.005 * length * h**2)  # Euler-Bernoulli tip sag = 0.5 % of L
    ref = (
        3
        * rho
        * G
        * length**4
        / (2 * E * h**2)
        * (1 + E / (3 * (5 / 6) * E / (2 * (1 + nu))) * (h / length) ** 2)
    )
    b = 2 * dx
    # The clamp ends at x = 0, on a grid node: the clamped length is a whole number of cells.
    clamp_len = math.ceil(0.25 * length / dx) * dx
    p = Particles.lattice((-clamp_len, 0.0, 0.0), (length, b, h), dx / 2)
    clamp = VelocityBox((-length, -1.0, -1.0), (0.1 * dx, 1.0, 1.0))
    t1 = 2 * math.pi / 1.875**2 * length**2 * math.sqrt(12 * rho / (E * h**2))  # fundamental period
    scene = Scene(boxes=(clamp,), damping=4 * math.pi / t1)
    solver = _solver(
        p,
        MaterialParams("fixed_corotated", E, nu, rho),
        (-clamp_len, 0, -length / 4),
        (length, b, h + length / 8),
        dx,
        scene,
        frame_dt=t1 / 20,
    )
    tip = p.x[:, 0] > length - dx / 2
    z0 = float(p.x[tip, 2].mean())
    sag = []
    for _ in range(60):
        solver.step_frame()
        sag.append(z0 - float(solver.state().x[tip, 2].mean()))
    mean_sag = float(np.mean(sag[-20:]))
    return _result(
        "cantilever_tip_deflection",
        abs(mean_sag / ref - 1),
        0.05,
        measured_m=mean_sag,
        expected_m=ref,
        euler_bernoulli_m=3 * rho * G * length**4 / (2 * E * h**2),
    )


def angular_momentum(x, v, C, mass, dx) -> np.ndarray:
    """APIC angular momentum sum m (x cross v) + m (dx^2 / 4) eps : C^T, [3]."""
    d = 0.25 * dx**2
    spin = np.stack([C[:, 2, 1] - C[:, 1, 2], C[:, 0, 2] - C[:, 2, 0], C[:, 1, 0] - C[:, 0, 1]], axis=1)
    return (mass[:, None] * (np.cross(x, v) + d * spin)).sum(0)


def spinning_cube(fast: bool = True) -> dict:
    """An elastic cube spinning without gravity keeps its angular momentum."""
    sp = 0.0125 if fast else 0.00625
    dx = 2 * sp
    p = Particles.lattice((-0.1, -0.1, -0.1), (0.1, 0.1, 0.1), sp)
    omega = np.array([0.0, 2.0, 5.0])
    p.v = np.cross(omega, p.x)
    mat = MaterialParams("fixed_corotated", 1e5, 0.3, 1000.0)
    solver = _solver(p, mat, (-0.2, -0.2, -0.2), (0.2, 0.2, 0.2), dx, Scene(gravity=(0.0, 0.0, 0.0)))
    mass = (p.volume * mat.density).astype(np.float64)

    def momentum():
        s = solver.state()
        return angular_momentum(
            s.x.astype(np.float64), s.v.astype(np.float64), s.C.astype(np.float64), mass, dx
        )

    l0 = momentum()
    err = 0.0
    for _ in range(10 if fast else 50):
        solver.step_frame()
        err = max(err, float(np.linalg.norm(momentum() - l0) / np.linalg.norm(l0)))
    return _result("spinning_cube_angular_momentum", err, 0.01)


def _ball(radius: float, sp: float, center, material: int = 0) -> Particles:
    c = np.asarray(center, dtype=np.float64)
    return Particles.lattice(
        tuple(c - radius),
        tuple(c + radius),
        sp,
        material=material,
        inside=lambda x: ((x - c) ** 2).sum(1) < radius**2,
    )


def colliding_spheres(fast: bool = True) -> dict:
    """Two elastic spheres hit head-on: total energy within 5 % and they separate again."""
    sp = 0.0125 if fast else 0.00625
    r = 0.1
    a, b = _ball(r, sp, (-0.15, 0, 0)), _ball(r, sp, (0.15, 0, 0))
    a.v = np.tile([1.0, 0.0, 0.0], (len(a), 1))
    b.v = np.tile([-1.0, 0.0, 0.0], (len(b), 1))
    p = Particles.cat([a, b])
    left = np.arange(len(p)) < len(a)
    mat = MaterialParams("fixed_corotated", 1e6, 0.3, 1000.0)
    solver = _solver(
        p, mat, (-0.5, -0.15, -0.15), (0.5, 0.15, 0.15), 2 * sp, Scene(gravity=(0.0, 0.0, 0.0)), frame_dt=0.02
    )
    e0 = solver.energy().total
    for _ in range(10):  # contact at ~0.05 s, apart by ~0.12 s, the domain walls only at ~0.25 s
        solver.step_frame()
    s, e1 = solver.state(), solver.energy().total
    gap_speed = float(s.v[~left, 0].mean() - s.v[left, 0].mean())
    distance = float(s.x[~left, 0].mean() - s.x[left, 0].mean())
    separated = gap_speed > 0 and distance > 2 * r
    err = abs(e1 - e0) / e0
    return _result(
        "colliding_spheres_energy",
        err,
        0.05,
        passed=err <= 0.05 and separated,
        separated=bool(separated),
        separation_speed=gap_speed,
    )


def ball_restitution(
    fast: bool = True,
    E: float = 1e5,
    held_depth: float = 0.0,
    contact: str | None = None,
    damping: float | None = None,
) -> dict:
    """Elastic ball dropped on a slip, separating floor bounces back with restitution >= 0.7.

    contact, damping: ``GroundPlane``'s (None: its defaults)."""
    ground = GroundPlane(0.0, friction=0.0, mode="slip", held_depth=held_depth, contact=contact)
    if damping is not None:
        ground = replace(ground, damping=damping)
    sp = 0.0125 if fast else 0.00625
    r, height = 0.1, 0.2
    p = _ball(r, sp, (0.0, 0.0, r + height))
    mat = MaterialParams("fixed_corotated", E, 0.3, 1000.0)
    solver = _solver(
        p,
        mat,
        (-0.2, -0.2, 0.0),
        (0.2, 0.2, 2 * r + height),
        2 * sp,
        Scene(ground=ground),
        frame_dt=0.005,
    )
    vz = []
    t_impact = math.sqrt(2 * height / G)
    for _ in range(int((t_impact + 0.25) / 0.005)):
        solver.step_frame()
        vz.append(float(solver.state().v[:, 2].mean()))
    vz = np.array(vz)
    i = int(np.argmin(vz))
    e = float(vz[i:].max() / -vz[i])
    return _result(f"ball_restitution_E{E:.0e}", max(0.0, 0.7 - e), 0.0, restitution=e)


def pile_slope(x: np.ndarray, dx: float) -> float:
    """Slope angle (degrees) of a heap: line fit of the surface height between 20 % and 80 % of the top.

    The surface height of each radial ring of width dx is the 98th percentile of its particles' z.
    """
    r = np.hypot(x[:, 0] - x[:, 0].mean(), x[:, 1] - x[:, 1].mean())
    edges = np.arange(0.0, r.max() + dx, dx)
    ring = np.digitize(r, edges)
    centers, tops = [], []
    for k in range(1, len(edges)):
        z = x[ring == k, 2]
        if len(z) > 3:
            centers.append(0.5 * (edges[k - 1] + edges[k]))
            tops.append(np.percentile(z, 98))
    centers, tops = np.array(centers), np.array(tops)
    band = (tops > 0.2 * tops.max()) & (tops < 0.8 * tops.max())
    slope = np.polyfit(centers[band], tops[band], 1)[0]
    return float(math.degrees(math.atan(-slope)))


def sand_pile(
    fast: bool = True,
    friction_angle: float = 35.0,
    sp: float | None = None,
    radius: float | None = None,
    height: float | None = None,
    seconds: float | None = None,
    model: str = "mohr_coulomb",
) -> dict:
    """A steep cone of cohesionless sand slumps into a heap whose slope is the friction angle.

    ``model``: the granular constitutive model (the material table's sand is mohr_coulomb).

    The heap is formed quasi-statically: a mass-proportional drag (20 1/s) removes the inertia
    that would otherwise carry the avalanche past the angle of repose, so the measured slope is
    the static limit of the Drucker-Prager material, not a run-out.
    """
    sp = sp or (0.006 if fast else 0.005)
    radius = radius or (0.08 if fast else 0.12)  # >= 7 cells: coarser heaps stand a few degrees steeper
    height = height or (0.13 if fast else 0.2)
    seconds = seconds or (1.0 if fast else 1.5)
    p = Particles.lattice(
        (-radius, -radius, 0.0),
        (radius, radius, height),
        sp,
        inside=lambda x: np.hypot(x[:, 0], x[:, 1]) < radius * (1 - x[:, 2] / height),
    )
    mat = MaterialParams(model, 3.5e5, 0.3, 1600.0, friction_angle=friction_angle)
    reach = radius + 2 * height
    scene = Scene(ground=GroundPlane(0.0, mode="sticky"), damping=20.0)
    solver = _solver(p, mat, (-reach, -reach, 0.0), (reach, reach, height), 2 * sp, scene)
    for _ in range(int(seconds / 0.04)):
        solver.step_frame()
    angle = pile_slope(solver.state().x.astype(np.float64), 2 * sp)
    return _result(
        f"sand_pile_slope_{model}",
        abs(angle - friction_angle),
        5.0,
        slope_deg=angle,
        friction_angle_deg=friction_angle,
        units="degrees",
    )


def all_cases(fast: bool = True) -> list[Callable[[], dict | list[dict]]]:
    """Every verification case as a zero-argument callable."""
    return [
        lambda: free_fall(fast),
        lambda: resting_block(fast),
        lambda: bar_vibration(fast),
        lambda: cantilever(fast),
        lambda: spinning_cube(fast),
        lambda: colliding_spheres(fast),
        lambda: ball_restitution(fast, E=1e5),
        *([] if fast else [lambda: ball_restitution(fast, E=1e7)]),
        lambda: sand_pile(fast),
        *[lambda a=a: column_collapse(a, cells=FAST_CELLS[a] if fast else FULL_CELLS) for a in ASPECTS],
    ]
