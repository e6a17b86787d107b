"""Simulation planner: the cheapest simulation whose visual error stays under a pixel bound.

Inputs are the object (rest particles), its physics (material, E, nu, density), the scene
(gravity, ground, prescribed boxes, initial velocities) and the output cameras. The planner
converts physical deformation estimates to pixels with the cameras' focal length over depth and
chooses, in order of cost:

1. **rigid**: if the elastic + plastic deformation the scene can cause stays under the bound
   (a steel or ceramic object dropped on the floor or thrown at a still wall); granular and fluid
   materials never go rigid, nor do scenes that prescribe motion (grips, clamps).
2. **MPM with a stiffness cap**: the explicit step scales as dx / c_p with the P-wave speed
   c_p ~ sqrt(E / rho), so a stiff object costs many sub-steps. The cap is the smallest E' whose
   *extra* deformation over the true E stays under (a share of) the bound; E' = min(E, cap) is
   simulated and reported. Not after an elastic impact, whose rebound depends on E (see the
   comment in ``plan_simulation``).
   Before it, a **bulk cap** (``physgm.sim.bulk_cap``) lowers only the bulk modulus of a nearly
   incompressible solid (rubber, jelly) so its P-wave is at most ``bulk_wave_ratio`` times its
   shear wave, within its own share of the bound (that one also counts the rebound).
3. **MPM at full stiffness** (the reference).

Deformation model (object size L, density rho, impact speed v, P-wave speed c_p):
    sag under gravity          d_sag  = rho g L^2 / E
    elastic impact compression d_imp  = v L / c_0        (c_0 = sqrt(E / rho): 1/2 m v^2 = 1/2 (E L) d^2)
    plastic dent past yield    d_pl   = rho L v^2 / (2 sigma_y)   if rho c_p v > sigma_y
All three are order-of-magnitude estimates: the plan reports them so the choice can be audited.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from torch import Tensor

from physgm.cameras import Cameras
from physgm.sim.bulk_cap import choose_bulk_cap, rebound_px
from physgm.sim.constitutive import MODELS, MaterialParams
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.stepping import substeps_per_frame
from physgm.sim.rigid import static_walls

# Constitutive models whose material flows instead of springing back: never rigid.
FLOWING_MODELS = frozenset({"drucker_prager", "mohr_coulomb", "fluid"})
GRANULAR_MODELS = frozenset({"drucker_prager", "mohr_coulomb"})  # pour into a heap at their friction angle


@dataclass
class PlannerConfig:
    """Planner knobs (conf/sim/planner/default.yaml)."""

    bound_px: float = 0.5  # largest visual error allowed, pixels at the output resolution
    cells_across: int = 12  # grid cells across the object's largest extent
    max_cells: int = 96  # cap on grid cells per axis (dx grows to respect it)
    # MPM particles per grid cell: 8 (2 per axis) is MPM practice; at 1 per cell or fewer a soft
    # body loses its shape. Sets the particle spacing dx / ppc^(1/3); the lattice through the
    # object's bounding box then holds at most (cells_across ppc^(1/3))^3 particles (13,824).
    particles_per_cell: float = 8.0
    min_opacity: float = 0.05  # Gaussians fainter than this carry no mass
    fill_interior: bool = True  # fill the inside of closed Gaussian shells with particles (sampling.py)
    follower_k: int = 8  # nearest particles each Gaussian follows
    allow_rigid: bool = True  # rigid-body path for objects that would not deform visibly
    allow_stiffness_cap: bool = True  # lower E while the extra deformation stays under the bound
    min_cap_gain: float = 1.25  # cap only if it saves at least this factor of sub-steps
    cap_budget: float = 0.5  # fraction of bound_px the stiffness cap may use (rebound changes too)
    # Bulk cap (sim/bulk_cap.py): keep the shear modulus, lower nu until c_p <= ratio c_s. It may
    # use bound_px minus the stiffness cap's share, and counts the rebound of an elastic impact.
    allow_bulk_cap: bool = True
    bulk_wave_ratio: float = 2.0  # smallest c_p / c_s the bulk cap may reach (2: nu = 1/3)
    force_caps: bool = False  # benchmarks: take each allowed cap whatever its predicted error
    # Cap E after an elastic impact too: far fewer sub-steps for stiff objects thrown at a wall,
    # but the rebound then differs by pixels (measured 3 px) beyond the bound: predicted_error_px
    # counts them (bulk_cap.rebound_px), the bound does not limit them.
    cap_elastic_impacts: bool = False
    cfl: float = 0.4  # CFL number for predicting sub-steps (the solver's config runs)
    rigid_dt: float = 1e-3  # rigid-body step, s
    restitution: float = 0.6  # rigid-path ground restitution (the material table has none)
    rest_px: float = 0.05  # a frame is still when no particle moved more than this, pixels
    rest_frames: int = 5  # still frames in a row before the remaining frames are held
    spread_factor: float = 0.5  # horizontal grid margin for sagging / splashing, object sizes
    ballistic: bool = True  # free flight before the first contact in closed form
    fit_grid: bool = True  # False: a fixed cube of domain_size on the ground (naive baseline)
    domain_size: float = 1.0  # m, only with fit_grid = False

    def __post_init__(self) -> None:
        positive = ("bound_px", "cells_across", "max_cells", "particles_per_cell", "cfl", "rigid_dt")
        for name in (*positive, "domain_size"):
            if not getattr(self, name) > 0:
                raise ValueError(f"planner setting {name}={getattr(self, name)!r} must be > 0")
        if not self.bulk_wave_ratio > 1.0:
            raise ValueError(f"planner bulk_wave_ratio={self.bulk_wave_ratio!r} must be > 1 (c_p > c_s)")
        if not 0.0 <= self.cap_budget <= 1.0:
            raise ValueError(f"planner cap_budget={self.cap_budget!r} must be in [0, 1]")
        if not 0.0 <= self.restitution <= 1.0:
            raise ValueError(f"planner restitution={self.restitution!r} must be in [0, 1]")


@dataclass
class Deformation:
    """Estimated visible deformation of the object in the scene, metres."""

    sag: float
    impact: float
    plastic: float
    flows: bool  # granular / fluid / prescribed motion: unbounded

    @property
    def total(self) -> float:
        return math.inf if self.flows else self.sag + self.impact + self.plastic


@dataclass
class Plan:
    """What to simulate and why.

    Attributes:
        mode: "rigid" or "mpm".
        E_requested, E_used: Young's modulus asked for and simulated (after the caps), Pa.
        nu_requested, nu_used: Poisson ratio asked for and simulated (after the bulk cap).
        predicted_error_px: visual error of this plan relative to full-stiffness MPM, pixels.
        error_terms: named parts of the estimate, pixels.
        px_per_m: pixels per metre at the object for the closest output camera.
        grid_lo, grid_hi: [3] reachable region the grid must hold, m (before boundary margin).
        dx: grid cell size, m.  particle_spacing: m.
        substeps_per_frame: predicted (rigid: integration steps per frame).
        predicted_cost: predicted particle-substeps (rigid: body steps).
        rest_px, rest_frames: early stop once no particle moved more than rest_px pixels per
            frame for rest_frames frames.
        reason: one human-readable sentence.
        walls: contact planes ((n, d), ...) of the scene's still walls, for the rigid path.
    """

    mode: str
    material: str
    E_requested: float
    E_used: float
    nu_requested: float
    nu_used: float
    predicted_error_px: float
    error_terms: dict[str, float]
    px_per_m: float
    grid_lo: np.ndarray
    grid_hi: np.ndarray
    dx: float
    particle_spacing: float
    n_particles: int
    substeps_per_frame: int
    predicted_cost: float
    frame_dt: float
    n_frames: int
    rest_px: float
    rest_frames: int
    restitution: float
    reason: str
    alternatives: dict[str, float] = field(default_factory=dict)  # mode -> predicted cost
    walls: list = field(default_factory=list)

    def summary(self) -> dict:
        """JSON-friendly view (grid as cell counts)."""
        out = {k: v for k, v in asdict(self).items() if not isinstance(v, np.ndarray)}
        out["grid_cells"] = [int(math.ceil(c)) for c in (self.grid_hi - self.grid_lo) / self.dx]
        return out


def pixels_per_metre(
    cameras: Cameras,
    points: Tensor,  # [P, 3] world points of the object, m
) -> float:
    """Largest image-plane scale f / depth over cameras and points (the closest view), px/m."""
    pts = points.detach().to(cameras.c2w)
    cam = pts @ cameras.viewmats[:, :3, :3].transpose(-1, -2) + cameras.viewmats[:, None, :3, 3]  # [C, P, 3]
    depth = cam[..., 2]
    if not (depth > 0).any():
        raise ValueError(
            "the object is behind every output camera; check the cameras' c2w (OpenCV: +z looks forward)"
        )
    focal = torch.maximum(cameras.Ks[:, 0, 0], cameras.Ks[:, 1, 1])  # [C]
    # A point at depth ~0 would give an infinite scale; the object cannot come closer than 1 mm.
    scale = focal[:, None] / depth.clamp_min(1e-3)
    return float(scale[depth > 0].max())


def deformation_estimate(
    E: float,  # Pa
    density: float,  # kg/m^3
    size: float,  # largest object extent, m
    impact_speed: float,  # m/s
    gravity: float = 9.81,  # m/s^2
    yield_stress: float | None = None,  # Pa; None: purely elastic
    flows: bool = False,
    wave_factor: float = 1.0,  # P-wave modulus / E, e.g. (1 - nu) / ((1 + nu)(1 - 2 nu))
) -> Deformation:
    """Order-of-magnitude deformation of the object in metres (see module docstring).

    Both choices are the conservative ones: the compression uses the bar speed sqrt(E / rho) (a
    free block, larger than the constrained P-wave estimate), the impact stress the P-wave speed
    sqrt(wave_factor E / rho) (larger stress, earlier yield).
    """
    if E <= 0 or density <= 0 or size <= 0:
        raise ValueError(
            f"deformation_estimate needs positive E, density and size, got {E}, {density}, {size}"
        )
    sag = density * gravity * size**2 / E
    impact = impact_speed * size / math.sqrt(E / density)
    c_p = math.sqrt(wave_factor * E / density)
    plastic = 0.0
    if yield_stress is not None and yield_stress > 0:
        if density * gravity * size > yield_stress:
            flows = True  # slumps under its own weight
        elif density * c_p * impact_speed > yield_stress:  # impact stress rho c_p v
            plastic = density * size * impact_speed**2 / (2 * yield_stress)
    return Deformation(sag, impact, plastic, flows)


def stiffness_cap(
    E: float,  # Pa, true stiffness
    density: float,  # kg/m^3
    size: float,  # m
    impact_speed: float,  # m/s
    bound: float,  # extra deformation allowed, m
    gravity: float = 9.81,
) -> float:
    """Smallest E' <= E whose elastic deformation exceeds that at E by at most ``bound``, Pa.

    Elastic deformation is a / E + b / sqrt(E) (sag + impact); with u = 1 / sqrt(E') the
    condition a u^2 + b u = d(E) + bound is a quadratic with one positive root.
    Monotone: a larger bound gives a smaller (cheaper) cap.
    """
    if bound < 0:
        raise ValueError(f"bound must be >= 0, got {bound}")
    a = density * gravity * size**2
    b = impact_speed * size * math.sqrt(density)
    target = a / E + b / math.sqrt(E) + bound
    if a > 0:
        u = (-b + math.sqrt(b * b + 4 * a * target)) / (2 * a)
    elif b > 0:
        u = target / b
    else:
        return E
    return min(E, 1.0 / (u * u))


def impact_speed(z_bottom: float, ground: float | None, vz0: float, gravity: float) -> float:
    """Speed at which the lowest point reaches the ground (0 without a ground), m/s."""
    if ground is None:
        return abs(vz0)
    fall = max(z_bottom - ground, 0.0)
    return math.sqrt(vz0 * vz0 + 2 * gravity * fall) if vz0 <= 0 or fall > 0 else abs(vz0)


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

    Falls to the ground (or freely for ``duration``), tumbles about its centre, rises by
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


# Materials that never go rigid whatever their stiffness (granular: they pour and heap).
NEVER_RIGID_MATERIALS = frozenset({"sand", "snow"})


def choose_spacing(size: float, config: PlannerConfig) -> tuple[float, float]:
    """(grid dx, particle spacing) in m for an object of largest extent ``size`` (m)."""
    if not size > 0:
        raise ValueError(f"object size must be positive, got {size} m; are all Gaussians at one point?")
    dx = size / config.cells_across
    return dx, dx / config.particles_per_cell ** (1 / 3)


def plan_simulation(
    x: Tensor,  # [P, 3] rest particles, m
    volume: Tensor,  # [P] rest volumes, m^3
    v0: Tensor,  # [P, 3] initial velocities, m/s
    name: str,
    material: MaterialParams,
    scene: Scene,
    cameras: Cameras,
    n_frames: int,
    frame_dt: float,
    dx: float,
    particle_spacing: float,
    config: PlannerConfig | None = None,
) -> Plan:
    """Choose rigid / MPM with capped E / MPM, fit the grid and set early stop; see module doc.

    Args:
        name: material name (granular names never go rigid).
        n_frames: output frames including the rest frame 0.
        dx, particle_spacing: from ``choose_spacing`` (dx may grow to respect ``max_cells``).
    """
    cfg = config or PlannerConfig()
    if n_frames < 1 or frame_dt <= 0:
        raise ValueError(f"need n_frames >= 1 and frame_dt > 0, got {n_frames} and {frame_dt}")
    pts = x.detach().double().cpu()
    lo, hi = pts.min(0).values.numpy(), pts.max(0).values.numpy()
    size = float((hi - lo).max())
    gravity = np.asarray(scene.gravity, dtype=np.float64)
    g = float(np.linalg.norm(gravity))
    ground = None if scene.ground is None else float(scene.ground.height)
    vel = v0.detach().double().cpu().numpy().reshape(-1, 3)
    duration = (n_frames - 1) * frame_dt  # frame 0 is the rest state
    box_speed = max((float(np.linalg.norm(b.velocity)) for b in scene.boxes), default=0.0)
    v_impact = impact_speed(float(lo[2]), ground, float(vel[:, 2].min(initial=0.0)), g)
    v_throw = float(np.linalg.norm(vel, axis=1).max(initial=0.0))
    # The loading speed: an impact on the ground or a wall, or grips pulling (the elastic lag is
    # the same v L / c).
    v_load = max(v_impact, box_speed, v_throw)
    v_max = max(v_load, float(np.linalg.norm(vel, axis=1).max(initial=0.0)))

    # Pixel scale: the object where it starts and where it lands, seen by the closest camera.
    landed = pts.clone()
    if ground is not None:
        landed[:, 2] -= float(lo[2]) - ground
    px_per_m = max(pixels_per_metre(cameras, pts.float()), pixels_per_metre(cameras, landed.float()))

    flows = material.model in FLOWING_MODELS or name in NEVER_RIGID_MATERIALS
    yield_stress = (
        material.yield_stress if MODELS[material.model].plastic and material.yield_stress > 0 else None
    )
    wave_factor = material.wave_speed() ** 2 * material.density / material.E
    deform = deformation_estimate(
        material.E, material.density, size, v_load, g, yield_stress, flows, wave_factor
    )
    terms = {"sag_px": deform.sag * px_per_m, "impact_px": deform.impact * px_per_m}
    terms["plastic_px"] = deform.plastic * px_per_m

    g_lo, g_hi, grid_dx = _grid_region(cfg, material, x, v0, volume, scene, duration, dx, ground)
    n_nodes = int(np.prod(np.ceil((g_hi - g_lo) / grid_dx) + 9))  # + boundary margins of GridSpec.fit
    steps = {"mpm": substeps_per_frame(grid_dx, [material], v_max, cfg.cfl, frame_dt)}
    steps["rigid"] = max(1, math.ceil(frame_dt / cfg.rigid_dt - 1e-9))
    P = len(pts)
    cost = {"mpm": float((n_frames - 1) * steps["mpm"] * P), "rigid": float((n_frames - 1) * steps["rigid"])}
    common = dict(
        material=name,
        E_requested=material.E,
        nu_requested=material.nu,
        px_per_m=px_per_m,
        grid_lo=g_lo,
        grid_hi=g_hi,
        dx=grid_dx,
        particle_spacing=particle_spacing,
        n_particles=P,
        frame_dt=frame_dt,
        n_frames=n_frames,
        rest_px=cfg.rest_px,
        rest_frames=cfg.rest_frames,
        restitution=cfg.restitution,
        alternatives=cost,
    )
    rigid_px = deform.total * px_per_m
    walls = static_walls(scene.boxes, lo, hi)  # still walls are contact planes of the rigid path
    if walls is not None:  # side walls too; a periodic axis has no rigid counterpart
        walls = None if scene.periodic else walls + [w.plane() for w in scene.walls]
    if cfg.allow_rigid and walls is not None and rigid_px <= cfg.bound_px:
        parts = ", ".join(f"{k[:-3]} {v:.2g}" for k, v in terms.items())
        reason = (
            f"{name} (E={material.E:.3g} Pa) deforms ~{rigid_px:.3g} px <= {cfg.bound_px} px ({parts}): "
            "rigid body"
        )
        return Plan(
            "rigid",
            E_used=material.E,
            nu_used=material.nu,
            predicted_error_px=rigid_px,
            error_terms=terms,
            substeps_per_frame=steps["rigid"],
            predicted_cost=cost["rigid"],
            reason=reason,
            walls=walls,
            **common,
        )
    if flows:
        why = "it flows (granular / fluid)"
    elif walls is None:
        why = "the scene prescribes motion"
    elif not cfg.allow_rigid:
        why = "rigid mode is disabled"
    else:
        why = f"it deforms ~{rigid_px:.3g} px > {cfg.bound_px} px"

    # Stiffness cap (see module doc). It may use only ``cap_budget`` of the bound: the deformation
    # estimate does not see that a softer body also rebounds differently. After an elastic impact
    # (a drop or a push without a visible dent) the rebound decides the trajectory, and E moves it
    # far more than the squash: measured on a bouncing 15 cm plastic block (E = 5e7 Pa, 256 px),
    # E 20 % lower moved it 1.3 px on average, the capped 2.4e7 Pa 3.2 px, while the deformation
    # estimate promised 0.25 px. So an elastic impact is never capped; quasi-static loading
    # (grips) and impacts that end in a plastic dent (the rebound is small) are.
    # (A body resting on the ground, its lowest particles half a spacing up, does not impact; nor
    # does one a cell up: the grid does not resolve the gap, and sqrt(2 g dx) is a tap.)
    falls = ground is not None and float(lo[2]) - ground > dx
    elastic_impact = (falls or v_throw > 0.0) and deform.plastic * px_per_m <= cfg.bound_px
    simulated, n_steps, notes, cap_px, bulk_px = material, steps["mpm"], [], 0.0, 0.0
    cap_impacts = cfg.cap_elastic_impacts or cfg.force_caps
    caps_E = cfg.allow_stiffness_cap and (cap_impacts or not elastic_impact)
    if cfg.allow_bulk_cap and not flows:

        def deformation_px(modulus: float) -> float:
            d = deformation_estimate(modulus, material.density, size, v_load, g)
            return (d.sag + d.impact) * px_per_m

        share = cfg.bound_px * (1.0 - (cfg.cap_budget if caps_E else 0.0))
        object_px = size * px_per_m
        bulk = choose_bulk_cap(
            material, deformation_px, object_px, elastic_impact, share, cfg.bulk_wave_ratio, cfg.force_caps
        )
        bulk_steps = bulk and substeps_per_frame(grid_dx, [bulk.material], v_max, cfg.cfl, frame_dt)
        if bulk is not None and (cfg.force_caps or n_steps >= cfg.min_cap_gain * bulk_steps):
            notes.append(
                f"bulk capped to nu={bulk.material.nu:.3g} (c_p = {bulk.ratio:.3g} c_s; {n_steps} -> "
                f"{bulk_steps} sub-steps/frame, ~{bulk.predicted_px:.2g} px)"
            )
            simulated, n_steps, bulk_px = bulk.material, bulk_steps, bulk.predicted_px
            terms["bulk_cap_rebound_px"] = bulk.rebound_px
    terms["bulk_cap_px"] = bulk_px
    if cfg.allow_stiffness_cap and not caps_E:
        notes.append(
            "E not capped (an elastic impact: the rebound depends on E; planner.cap_elastic_impacts)"
        )
    elif caps_E:
        bound = cfg.cap_budget * cfg.bound_px / px_per_m
        cap = stiffness_cap(simulated.E, material.density, size, v_load, bound, g)
        cap_steps = substeps_per_frame(grid_dx, [simulated.with_elasticity(E=cap)], v_max, cfg.cfl, frame_dt)
        if n_steps >= cfg.min_cap_gain * cap_steps:
            notes.append(f"E capped to {cap:.3g} Pa ({n_steps} -> {cap_steps} sub-steps/frame)")
            soft = deformation_estimate(cap, material.density, size, v_load, g)
            hard = deformation_estimate(simulated.E, material.density, size, v_load, g)
            cap_px = (soft.sag + soft.impact - hard.sag - hard.impact) * px_per_m
            softer = simulated.with_elasticity(E=cap)
            if elastic_impact:  # opted in: the rebound error is predicted, not bounded
                terms["stiffness_cap_rebound_px"] = rebound_px(simulated, softer, size * px_per_m)
                cap_px += terms["stiffness_cap_rebound_px"]
            simulated, n_steps = softer, cap_steps
    terms["stiffness_cap_px"] = cap_px
    cost["mpm_capped"] = float((n_frames - 1) * n_steps * P)
    note = "".join(f"; {n}" for n in notes)
    reason = f"MPM because {why}{note}; grid {n_nodes} nodes, dx={grid_dx:.3g} m"
    return Plan(
        "mpm",
        E_used=simulated.E,
        nu_used=simulated.nu,
        predicted_error_px=cap_px + bulk_px,
        error_terms=terms,
        substeps_per_frame=n_steps,
        predicted_cost=cost["mpm_capped"],
        reason=reason,
        **common,
    )


def _grid_region(
    cfg: PlannerConfig,
    material: MaterialParams,
    x: Tensor,  # [P, 3] m
    v0: Tensor,  # [P, 3] m/s
    volume: Tensor,  # [P] m^3
    scene: Scene,
    duration: float,
    dx: float,
    ground: float | None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """(lo [3], hi [3], dx) of the grid: the reachable region, or the naive fixed cube."""
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
    grid_dx = max(dx, float((g_hi - g_lo).max()) / cfg.max_cells)
    cells = np.ceil(2.0 * half / grid_dx - 1e-9)
    g_lo[:2], g_hi[:2] = centre - 0.5 * cells * grid_dx, centre + 0.5 * cells * grid_dx
    return g_lo, g_hi, grid_dx
