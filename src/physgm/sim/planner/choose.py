"""``plan_simulation``: the choice between rigid, MPM with capped stiffness, and full MPM.

See the package docstring (``physgm.sim.planner``) for the order of the options; the error model
of each is in ``deformation.py`` (and ``physgm.sim.bulk_cap``), the grid in ``domain.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from torch import Tensor

from physgm.cameras import Cameras
from physgm.sim.bulk_cap import choose_bulk_cap, rebound_px, wave_shift_px
from physgm.sim.constitutive import MODELS, MaterialParams
from physgm.sim.mpm.pressure import (
    PRESSURE_MIN_CELLS,
    PRESSURE_MODELS,
    PRESSURE_STEP_COST,
    scene_extras,
    shear_part,
    thinnest_extent,
)
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.stepping import implicit_step_speed, substeps_per_frame
from physgm.sim.planner.config import PlannerConfig
from physgm.sim.planner.deformation import (
    STIFFNESS_DENT_GAIN,
    deformation_estimate,
    impact_speed,
    pixels_per_metre,
    stiffness_cap,
    stiffness_dent_floor,
)
from physgm.sim.planner.domain import grid_region
from physgm.sim.planner.plan import Plan
from physgm.sim.rigid import static_walls

# Constitutive models whose material flows instead of springing back: never rigid.
FLOWING_MODELS = frozenset({"drucker_prager", "mohr_coulomb", "fluid"})

# Materials that never go rigid whatever their stiffness (granular: they pour and heap).
NEVER_RIGID_MATERIALS = frozenset({"sand", "snow"})


@dataclass
class _Choice:
    """One way to run the MPM: the material simulated, its sub-steps per frame and why."""

    material: MaterialParams
    steps: int
    notes: list[str] = field(default_factory=list)
    bulk_px: float = 0.0  # predicted error of the bulk cap, pixels
    cap_px: float = 0.0  # of the stiffness cap
    terms: dict[str, float] = field(default_factory=dict)  # the caps' own error terms


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
    integrator: str = "explicit",
    implicit_dt: float = 0.01,
) -> Plan:
    """Choose rigid / MPM with capped E / MPM, fit the grid and set early stop; see module doc.

    Args:
        name: material name (granular names never go rigid).
        n_frames: output frames including the rest frame 0.
        dx, particle_spacing: from ``choose_spacing`` (dx may grow to respect ``max_cells``).
        integrator: the MPM solver's (``SolverConfig.integrator``). With ``"pressure"`` the
            explicit step follows the material's shear part (``mpm.pressure.shear_part``): the
            sub-steps are predicted from it, and the bulk cap, which would only soften the volume
            term the grid takes implicitly, is not offered. With ``"implicit"``
            (``mpm.implicit``) the sub-step is ``implicit_dt`` (s) while the body is slow and the
            advective limit cfl dx / |v|max when it is fast, and neither cap is offered: neither
            would save a step. With ``"explicit"`` and ``config.allow_pressure`` the planner
            runs an elastic body with the pressure split instead where that pays
            (``Plan.integrator`` says which runs).
    """
    cfg = config or PlannerConfig()
    pressure = integrator == "pressure"
    implicit = integrator == "implicit"
    if implicit and not implicit_dt > 0.0:
        raise ValueError(f"implicit_dt={implicit_dt!r} s must be > 0")

    def stepped(m: MaterialParams, split: bool) -> MaterialParams:
        """The material whose P-wave sets the explicit step, with the pressure split or without."""
        return shear_part(m) if split else m

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
    # The body's lowest point is its material's, half a particle spacing under the lowest centres.
    bottom = float(lo[2]) - 0.5 * particle_spacing
    v_impact = impact_speed(bottom, ground, float(vel[:, 2].min(initial=0.0)), g)
    v_throw = float(np.linalg.norm(vel, axis=1).max(initial=0.0))
    # The loading speed: an impact on the ground or a wall, or grips pulling (the elastic lag is
    # the same v L / c).
    v_load = max(v_impact, box_speed, v_throw)
    v_max = max(v_load, float(np.linalg.norm(vel, axis=1).max(initial=0.0)))

    # Pixel scale: the object where it starts and where it lands, seen by the closest camera.
    landed = pts.clone()
    if ground is not None:
        landed[:, 2] -= bottom - ground
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

    g_lo, g_hi, grid_dx = grid_region(cfg, material, x, v0, volume, scene, duration, dx, ground, frame_dt)
    cells_across = cfg.cells_across * dx / grid_dx  # fewer than asked when the region coarsened it
    n_nodes = int(np.prod(np.ceil((g_hi - g_lo) / grid_dx) + 9))  # + boundary margins of GridSpec.fit
    speed = implicit_step_speed(cfg.cfl, grid_dx, implicit_dt) if implicit else None

    def mpm_steps(m: MaterialParams, split: bool) -> int:
        return substeps_per_frame(grid_dx, [stepped(m, split)], v_max, cfg.cfl, frame_dt, speed)

    steps = {"mpm": mpm_steps(material, pressure)}
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
        cells_across=cells_across,
        n_particles=P,
        frame_dt=frame_dt,
        n_frames=n_frames,
        rest_px=cfg.rest_px,
        rest_frames=cfg.rest_frames,
        rest_budget_px=cfg.rest_budget_px,
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
            integrator=integrator,
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
    # estimate promised 0.25 px. So an elastic impact is never capped; resting bodies are, and
    # impacts that end in a plastic dent as far as the dent's own term allows (a lower E moves the
    # dent with the wave speed: deformation.STIFFNESS_DENT_GAIN). Nor is a body that moving boxes drive
    # (grips, pushers): neither cap's model holds there. The stretch scene (0.2 m, pulled to twice
    # its length) moved 1.47 px with rubber's E capped (0.25 px predicted), 1.32 px with both caps
    # (0.39) and 2.55 px with a jelly's bulk capped (0.5): the stretch's necking follows nu, its
    # ringing when the grips stop follows E (docs/measurements_sim.md section 20).
    # (A body resting on the ground does not impact; nor does one a cell up: the grid does not
    # resolve the gap, and sqrt(2 g dx) is a tap.)
    # Nor is a material that flows: how far a granular body runs out follows E, which the
    # deformation estimate does not see. A 15 cm cube of sand set on the ground and left to
    # collapse (256 px, 50 frames), capped from 3.5e5 to 1.9e5 Pa with 0.25 px predicted, ended
    # 1.31 px from the full-stiffness run on average; dropped from 0.5 m, E 5 % lower moved it
    # 0.72 px (docs/measurements_sim.md section 32).
    falls = ground is not None and bottom - ground > dx
    impacts = falls or v_throw > 0.0
    elastic_impact = impacts and deform.plastic * px_per_m <= cfg.bound_px
    dent = impacts and not elastic_impact  # it lands and yields: no rebound (bulk_cap.dent_px)
    cap_impacts = cfg.cap_elastic_impacts or cfg.force_caps
    driven = box_speed > 0.0 and not cfg.force_caps
    runs_out = flows and not cfg.force_caps
    caps_E = (
        cfg.allow_stiffness_cap
        and (cap_impacts or not elastic_impact)
        and not (driven or runs_out or implicit)
    )
    size_px = size * px_per_m

    def with_bulk_cap(share: float, split: bool) -> _Choice:
        """Full stiffness, or the bulk cap within ``share`` px if it saves min_cap_gain."""
        full = _Choice(material, mpm_steps(material, split))
        if not cfg.allow_bulk_cap or flows or driven or split or implicit:
            return full

        def deformation_px(modulus: float) -> float:
            d = deformation_estimate(modulus, material.density, size, v_load, g)
            return (d.sag + (0.0 if dent else d.impact)) * px_per_m

        bulk = choose_bulk_cap(
            material,
            deformation_px,
            size_px,
            elastic_impact,
            share,
            cfg.bulk_wave_ratio,
            cfg.force_caps,
            dent=dent,
        )
        if bulk is None:
            return full
        bulk_steps = substeps_per_frame(grid_dx, [bulk.material], v_max, cfg.cfl, frame_dt)
        if not (cfg.force_caps or full.steps >= cfg.min_cap_gain * bulk_steps):
            return full
        note = (
            f"bulk capped to nu={bulk.material.nu:.3g} (c_p = {bulk.ratio:.3g} c_s; {full.steps} -> "
            f"{bulk_steps} sub-steps/frame, ~{bulk.predicted_px:.2g} px)"
        )
        own = {"bulk_cap_rebound_px": bulk.rebound_px, "bulk_cap_dent_px": bulk.dent_px}
        return _Choice(bulk.material, bulk_steps, [note], bulk_px=bulk.predicted_px, terms=own)

    def with_stiffness_cap(base: _Choice, split: bool) -> _Choice:
        """``base`` with E capped within cap_budget of the bound, if it saves min_cap_gain."""
        share_px = cfg.cap_budget * cfg.bound_px
        cap = stiffness_cap(base.material.E, material.density, size, v_load, share_px / px_per_m, g)
        if dent:  # the dent moves with the wave speed, which the deformation estimate does not see
            cap = max(cap, stiffness_dent_floor(base.material.E, share_px, size_px))
        softer = base.material.with_elasticity(E=cap)
        cap_steps = mpm_steps(softer, split)
        if base.steps < cfg.min_cap_gain * cap_steps:
            return base
        soft = deformation_estimate(cap, material.density, size, v_load, g)
        hard = deformation_estimate(base.material.E, material.density, size, v_load, g)
        cap_px = (soft.sag + soft.impact - hard.sag - hard.impact) * px_per_m
        own = dict(base.terms)
        if dent:  # the larger term counts, as for the bulk cap's dent
            own["stiffness_cap_dent_px"] = wave_shift_px(STIFFNESS_DENT_GAIN, base.material, softer, size_px)
            cap_px = max(cap_px, own["stiffness_cap_dent_px"])
        if elastic_impact:  # opted in: the rebound error is predicted, not bounded
            own["stiffness_cap_rebound_px"] = rebound_px(base.material, softer, size_px)
            cap_px += own["stiffness_cap_rebound_px"]
        note = f"E capped to {cap:.3g} Pa ({base.steps} -> {cap_steps} sub-steps/frame)"
        return _Choice(softer, cap_steps, base.notes + [note], base.bulk_px, cap_px, own)

    def capped(split: bool) -> _Choice:
        """The cheapest way to run the MPM within the bound, with the pressure split or without."""
        if not caps_E:
            return with_bulk_cap(cfg.bound_px, split)
        # The bound is shared when both caps apply; when the stiffness cap saves nothing, the bulk
        # cap alone may use all of it. The cheaper of the two is taken (the shared one on a tie).
        shared = with_stiffness_cap(with_bulk_cap(cfg.bound_px * (1.0 - cfg.cap_budget), split), split)
        alone = with_bulk_cap(cfg.bound_px, split)
        return alone if alone.steps < shared.steps else shared

    choice = capped(pressure)
    # The pressure split in place of explicit MPM, where its fewer sub-steps pay for its solve. It
    # is not a cap: the body keeps its E and nu. On a body at least PRESSURE_MIN_CELLS cells thick
    # its clip stays within 0.21 px of explicit's through the first contact and rebound, and is as
    # close to converged MPM as explicit's later (the rubber drop's mean distance to the
    # step-halving extrapolation over 30 frames: 1.64 px, explicit's 2.03; docs/measurements_sim.md
    # sections 42 and 45), so it adds no error term there; a thinner body keeps explicit.
    split_fits = (  # cheapest test first: the body's thickness is a pass over its particles
        integrator == "explicit"
        and cfg.allow_pressure
        and material.model in PRESSURE_MODELS
        and not scene_extras(scene)
        and thinnest_extent(pts.numpy(), particle_spacing) >= PRESSURE_MIN_CELLS * grid_dx * (1.0 - 1e-6)
    )
    if split_fits:
        split = capped(True)
        cost["mpm_pressure"] = float((n_frames - 1) * split.steps * P)
        if choice.steps >= cfg.min_cap_gain * PRESSURE_STEP_COST * split.steps:
            split.notes.insert(
                0,
                f"the pressure split ({choice.steps} -> {split.steps} sub-steps/frame, each "
                f"~{PRESSURE_STEP_COST:g}x the cost)",
            )
            choice, pressure = split, True
    if pressure:
        choice.notes.append("the pressure integrator: the volume term implicit on the grid, no bulk cap")
        if elastic_impact:  # measured: the bench's rubber cube bounces a second time to 0.237 m against 0.275
            choice.notes.append(
                "it damps the volume vibration the impact excites, so the body rebounds lower than "
                "explicit's (docs/measurements_sim.md sections 31 and 42)"
            )
    if implicit:
        choice.notes.append(f"the implicit integrator: steps of up to {implicit_dt:.3g} s, no caps")
    elif driven and (cfg.allow_stiffness_cap or cfg.allow_bulk_cap):
        choice.notes.append("E and nu not capped (moving boxes drive the body: no error model holds)")
    elif runs_out and cfg.allow_stiffness_cap:
        choice.notes.append("E not capped (a flow: how far it runs out follows E, which no error model sees)")
    elif cfg.allow_stiffness_cap and not caps_E:
        choice.notes.append(
            "E not capped (an elastic impact: the rebound depends on E; planner.cap_elastic_impacts)"
        )
    terms.update(choice.terms)
    terms["bulk_cap_px"] = choice.bulk_px
    terms["stiffness_cap_px"] = choice.cap_px
    cost["mpm_capped"] = float((n_frames - 1) * choice.steps * P)
    note = "".join(f"; {n}" for n in choice.notes)
    reason = f"MPM because {why}{note}; grid {n_nodes} nodes, dx={grid_dx:.3g} m"
    if grid_dx > dx * (1.0 + 1e-6):
        reason += (
            f" (coarser than the {dx:.3g} m the object asks for, so the region it can reach fits "
            f"planner.max_cells={cfg.max_cells} cells: {cells_across:.1f} cells across it)"
        )
    return Plan(
        "mpm",
        E_used=choice.material.E,
        nu_used=choice.material.nu,
        predicted_error_px=choice.cap_px + choice.bulk_px,
        error_terms=terms,
        substeps_per_frame=choice.steps,
        predicted_cost=cost["mpm_capped"],
        reason=reason,
        integrator="pressure" if pressure else integrator,
        **common,
    )
