"""Where the planner puts the grid and how fine: cell size, particle spacing, reachable region.

The grid holds every place the object can reach during the run (``reachable_region``: the fall,
tumbling, toppling, throw drift, prescribed boxes; granular runout and heaps, fluid splash), mirrored about
the object's centre in x and y, with at most ``max_cells`` cells per axis.
"""

from __future__ import annotations

import math

import numpy as np
from torch import Tensor

from physgm.sim.coast import ballistic_frames
from physgm.sim.constitutive import MaterialParams
from physgm.sim.mpm.scene import Scene
from physgm.sim.planner.config import PlannerConfig

GRANULAR_MODELS = frozenset({"drucker_prager", "mohr_coulomb"})  # pour into a heap at their friction angle
# Points within this share of the object's extent above its lowest point are its base: what it
# stands on, and what it can topple about.
BASE_LAYER = 0.05
# A body that must lean less than this to bring its centre over the edge of its base may fall over
# (a landing or a push tips it); the grid then leaves room for it to lie down. A cube needs 45 deg.
TIP_ANGLE_DEG = 20.0
MAX_STRETCH_SPLITS = 4  # most particles per lattice site along a stretched axis (4x the cost)


def base_points(pts: np.ndarray) -> np.ndarray:  # pts [P, 3] m -> [B, 3]
    """The body's base: its points within ``BASE_LAYER`` of its extent above its lowest point."""
    extent = float((pts.max(0) - pts.min(0)).max())
    return pts[pts[:, 2] <= pts[:, 2].min() + BASE_LAYER * extent]


def tipping_angle(pts: np.ndarray) -> float:  # pts [P, 3] m
    """How far the body must lean, degrees, before its centre passes the edge of its base (the
    bounding rectangle of ``base_points``; 0 when the centre is already outside it)."""
    base = base_points(pts)
    center = pts.mean(0)
    inside = np.minimum(center[:2] - base[:, :2].min(0), base[:, :2].max(0) - center[:2]).min()
    height = center[2] - pts[:, 2].min()
    return math.degrees(math.atan2(max(float(inside), 0.0), max(float(height), 1e-12)))


def choose_spacing(size: float, config: PlannerConfig) -> tuple[float, float]:
    """(grid dx, particle spacing) in m for an object of largest extent ``size`` (m)."""
    if not size > 0:
        raise ValueError(f"object size must be positive, got {size} m; are all Gaussians at one point?")
    dx = size / config.cells_across
    return dx, dx / config.particles_per_cell ** (1 / 3)


def stretch_splits(ratio: float, spacing: float, dx: float, config: PlannerConfig) -> int:
    """Particles each lattice site becomes along the axis a scene stretches ``ratio`` x (1: none).

    Pulled apart, particles carry the body only while they stay within about a cell of each
    other, so the spacing along the axis, times the stretch, is kept below
    ``max_stretched_spacing`` cells (``sampling.split_along``). At most MAX_STRETCH_SPLITS: a
    body that thin somewhere is better given a finer grid (``cells_across``).
    """
    needed = math.ceil(ratio * spacing / (config.max_stretched_spacing * dx) - 1e-9)
    return min(max(1, needed), MAX_STRETCH_SPLITS)


def reachable_region(
    x: Tensor,  # [P, 3] rest particles, m
    v0: Tensor,  # [P, 3] initial velocities, m/s
    duration: float,  # s
    gravity: np.ndarray,  # [3] m/s^2
    ground: float | None,  # ground height, m
    spread: float,  # horizontal margin for tipping / flowing, m
    boxes: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]] = (),  # (lo, hi, velocity, moving time)
    friction: float = 0.0,  # ground Coulomb coefficient
) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box [lo, hi] (m) the object can reach during ``duration``.

    Falls to the ground (or freely for ``duration``), tumbles about its centre, topples over
    about a point of its base, rises by
    v0z^2 / 2g, drifts horizontally by |v0| T (or, with ground friction, flies until it lands
    and then slides v^2 / (2 mu g)), spreads by ``spread``, and follows any prescribed box it is
    gripped by. A ball rolling without resistance could go further: the domain walls stop it.
    """
    pts = x.detach().double().cpu().numpy()
    vel = v0.detach().double().cpu().numpy()
    lo, hi = pts.min(0), pts.max(0)
    # Tumbling: any point may end up anywhere within its distance of the centre; spreading
    # (sag, splash, heap) widens the footprint. Either margin covers the other.
    center = pts.mean(0)
    radius = float(np.linalg.norm(pts - center, axis=1).max())
    lo[:2] = np.minimum(lo[:2] - spread, center[:2] - radius)
    hi[:2] = np.maximum(hi[:2] + spread, center[:2] + radius)
    hi[2] = max(hi[2], center[2] + radius)
    if ground is not None and len(pts) and tipping_angle(pts) < TIP_ANGLE_DEG:
        # Toppling: a body that stands on a narrow base can fall over about a point p of it. Its
        # centre then ends within |c - p| of p and every point within the radius of the centre,
        # which reaches further than tumbling about the centre (a slab stood on end, or a
        # single-view reconstruction that is a thick disc on its rim: the grid faces stopped them).
        base = base_points(pts)
        reach = np.linalg.norm(base - center, axis=1)[:, None] + radius  # [B, 1]
        lo[:2] = np.minimum(lo[:2], (base[:, :2] - reach).min(0))
        hi[:2] = np.maximum(hi[:2], (base[:, :2] + reach).max(0))
    g = float(np.linalg.norm(gravity))
    vmax = np.abs(vel).max(0) if len(vel) else np.zeros(3)
    drift = vmax * duration
    vz_up = max(float(vel[:, 2].max()), 0.0) if len(vel) else 0.0
    if ground is not None and friction > 0 and g > 0:
        height = max(float(pts[:, 2].min()) - ground, 0.0)
        t_air = (vz_up + math.sqrt(vz_up**2 + 2 * g * height)) / g
        drift[:2] = np.minimum(drift[:2], vmax[:2] * t_air + vmax[:2] ** 2 / (2 * friction * g))
    lo[:2] -= drift[:2]
    hi[:2] += drift[:2]
    hi[2] += vz_up**2 / (2 * g) if g > 0 else vz_up * duration
    if ground is not None:
        lo[2] = min(lo[2], ground)
    else:
        lo[2] -= drift[2] + 0.5 * g * duration**2
    for b_lo, b_hi, b_vel, t_move in boxes:
        travel = np.asarray(b_vel, dtype=np.float64) * t_move
        lo = np.minimum(lo, np.minimum(b_lo, b_lo + travel))
        hi = np.maximum(hi, np.maximum(b_hi, b_hi + travel))
    return lo, hi


def heap_radius(volume: float, friction_angle_deg: float) -> float:
    """Radius of a cone of granular material of this volume at its angle of repose, m."""
    tan = math.tan(math.radians(max(friction_angle_deg, 5.0)))
    return (3 * volume / (math.pi * tan)) ** (1 / 3)


def granular_runout(
    size: float,  # object's largest horizontal extent, m
    top: float,  # height of the object's top above the ground, m (the fall adds to the column)
    friction_angle_deg: float,
    ground_friction: float | None,  # Coulomb coefficient of a "separate" ground; None: slip; inf: sticky
    duration: float,  # s
    gravity: float,  # m/s^2
) -> float:
    """How far (m) a granular object spreads past its own footprint radius on the ground.

    Lube et al. 2004 (J. Fluid Mech. 508) measured the runout of axisymmetric columns of radius
    R0 and height H on a rough base: (R - R0) / R0 = 1.24 a (a = H / R0 < 1.7), 1.6 a^(1/2)
    above. The released height counts the fall too (a dropped object is a taller column), and
    20 % is added for the experiments' scatter. A ground smoother than the material's friction
    lets the base slide further, by tan(phi) / mu; a frictionless one holds nothing back, so
    then the bound is the fall speed sqrt(2 g top) kept for the whole ``duration``.
    """
    r0 = 0.5 * size
    a = max(top, 0.0) / r0
    runout = 1.2 * r0 * (1.24 * a if a < 1.7 else 1.6 * math.sqrt(a))
    tan_phi = math.tan(math.radians(max(friction_angle_deg, 5.0)))
    if ground_friction is None:
        return runout + math.sqrt(2.0 * gravity * max(top, 0.0)) * duration
    return runout * max(1.0, tan_phi / max(ground_friction, 1e-3))


def grid_region(
    cfg: PlannerConfig,
    material: MaterialParams,
    x: Tensor,  # [P, 3] m
    v0: Tensor,  # [P, 3] m/s
    volume: Tensor,  # [P] m^3
    scene: Scene,
    duration: float,
    dx: float,
    ground: float | None,
    frame_dt: float | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """(lo [3], hi [3], dx) of the grid: the reachable region, or the naive fixed cube.

    A region wider than ``max_cells`` cells of ``dx`` along an axis coarsens the grid to fit, with
    one exception: a drop taller than that, whose fall until just before the first contact is
    computed in closed form (``coast.ballistic_frames``; needs ``frame_dt``), gets a grid of
    ``max_cells`` cells above the ground, which holds the body from where the simulation takes over,
    and which follows a rebound upwards (``mpm_run.followed_grid``). The landing is then simulated
    at the cell the body's size asks for, not at one stretched over the fall, which it does not
    need (docs/measurements_sim.md section 39).
    """
    pts = x.detach().double().cpu().numpy()
    lo, hi = pts.min(0), pts.max(0)
    if not cfg.fit_grid:
        center, half = 0.5 * (lo + hi), cfg.domain_size / 2
        g_lo = np.array([center[0] - half, center[1] - half, lo[2] if ground is None else ground])
        return g_lo, g_lo + cfg.domain_size, dx
    size = float((hi - lo).max())
    spread = cfg.spread_factor * size
    if material.model in GRANULAR_MODELS and ground is not None:  # collapses and runs out
        g_ground = scene.ground
        mu = {"slip": None, "sticky": math.inf}.get(g_ground.mode, g_ground.friction)
        footprint = float((hi[:2] - lo[:2]).max())
        g = float(np.linalg.norm(scene.gravity))
        runout = granular_runout(footprint, hi[2] - ground, material.friction_angle, mu, duration, g)
        spread = max(spread, runout)
    elif material.model in GRANULAR_MODELS:  # no ground: it falls as a cloud
        spread = max(spread, heap_radius(float(volume.sum()), material.friction_angle) - 0.5 * size)
    elif material.model == "fluid":
        spread = 2.0 * size
    boxes = [
        (
            np.asarray(b.lo),
            np.asarray(b.hi),
            np.asarray(b.velocity),
            max(0.0, min(b.stop, duration) - b.start),
        )
        for b in scene.boxes
    ]
    friction = scene.ground.friction if scene.ground is not None and scene.ground.mode == "separate" else 0.0
    g_lo, g_hi = reachable_region(x, v0, duration, np.asarray(scene.gravity), ground, spread, boxes, friction)
    # Horizontally the grid is mirror-symmetric about the particles' centre (a node or a cell
    # centre there): on a grid offset by a fraction of a cell, a symmetric body dropped flat meets
    # asymmetric stencils, its Coulomb friction at the ground pushes more on one side than the
    # other, and it drifts sideways (issue 24: ~1 mm in 2 s, docs/measurements_sim.md).
    centre = 0.5 * (lo[:2] + hi[:2])
    g_lo, g_hi = np.array(g_lo, dtype=np.float64), np.array(g_hi, dtype=np.float64)
    half = np.maximum(centre - g_lo[:2], g_hi[:2] - centre)
    g_lo[:2], g_hi[:2] = centre - half, centre + half
    grid_dx = max(dx, float((g_hi[:2] - g_lo[:2]).max()) / cfg.max_cells)
    height = float(g_hi[2] - g_lo[2])
    if height > cfg.max_cells * grid_dx:
        vel = v0.detach().double().cpu().numpy().reshape(-1, 3)
        top = landing_top(pts, vel, scene, frame_dt, duration, 3 * grid_dx) if _may_cut(cfg, scene) else None
        if top is not None and top <= g_lo[2] + cfg.max_cells * grid_dx:
            g_hi[2] = g_lo[2] + cfg.max_cells * grid_dx
        else:
            grid_dx = height / cfg.max_cells
    cells = np.ceil(2.0 * half / grid_dx - 1e-9)
    g_lo[:2], g_hi[:2] = centre - 0.5 * cells * grid_dx, centre + 0.5 * cells * grid_dx
    return g_lo, g_hi, grid_dx


def _may_cut(cfg: PlannerConfig, scene: Scene) -> bool:
    """The grid may be cut short of a drop's height: the fall is closed form and the grid may move."""
    return cfg.ballistic and cfg.follow and scene.grid_free


def landing_top(
    x: np.ndarray,  # [P, 3] rest particles, m
    v0: np.ndarray,  # [P, 3] initial velocities, m/s
    scene: Scene,
    frame_dt: float | None,  # s
    duration: float,  # s
    gap: float,  # m, the ballistic prefix's margin above the ground
) -> float | None:
    """Highest z (m) the body can reach from the frame where the simulation takes over from the
    closed-form fall until a frame later; None when no fall is computed in closed form."""
    if frame_dt is None or not frame_dt > 0:
        return None
    n_frames = int(round(duration / frame_dt)) + 1
    k0 = ballistic_frames(x, v0, scene, frame_dt, n_frames, gap)  # 1 without a ground to fall to
    if k0 <= 1:
        return None
    t = (k0 - 1) * frame_dt
    gz = float(scene.gravity[2])
    vz = float(v0[0, 2]) + gz * t
    top = float(x[:, 2].max()) + float(v0[0, 2]) * t + 0.5 * gz * t * t
    # A frame later it is lower (falling); a frame's reach still counts: the grid's check runs then.
    return top + abs(vz) * frame_dt + 0.5 * abs(gz) * frame_dt**2
