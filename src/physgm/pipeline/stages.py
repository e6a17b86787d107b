"""Photo (or views, or .ply) -> physically simulated clip: the stages and the run folder.

Stages, each timed in report.json: load (input + checkpoint), model (forward pass, physics
choice, placement), plan and simulate (``physgm.sim.gaussian_trajectory.simulate``), render
(deforming the Gaussians per frame + rasterising), write (videos, Gaussians over time, PLYs, contact
sheet, JSON, rename).
"""

from __future__ import annotations

import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from physgm.errors import UserError
from physgm.mp4 import write_mp4
from physgm.pipeline.config import RunConfig, from_hydra, scene_settings
from physgm.pipeline.outputs import (
    RunFolder,
    contact_sheet,
    keyframe_indices,
    plain_json,
    save_png,
    write_frame_plys,
    write_gif,
    write_json,
)

# Heavy modules (torch, warp) are imported inside the stages that need them, so a bad
# setting is reported in about a second and a .ply run never imports the model code.

STAGES = ("load", "model", "plan", "simulate", "render", "write")


@dataclass
class FutureResult:
    """One simulated future (the "mean" run or a posterior sample) as report.json records it."""

    name: str  # "mean" or "sample<k>"
    video: str  # file name in the run folder
    material: str
    E: float  # Pa, as chosen
    nu: float
    mode: str  # the planner's choice: rigid | mpm_capped | mpm
    integrator: str  # the MPM's time integration (solver.integrator, or the planner's pressure split)
    predicted_error_px: float
    error_terms: dict[str, float]  # the planner's named parts of its estimate, pixels
    px_per_m: float  # pixels per metre at the object in the closest output camera
    E_used: float  # Pa, as simulated (capped in mpm_capped)
    nu_used: float  # as simulated (lowered by the bulk-stiffness cap)
    particles: int
    grid_cells: list[int]  # along x, y, z
    dx_m: float
    cells_across: float  # grid cells across the object (the planner's cells_across unless coarsened)
    substeps: int
    rest_frame: int | None
    face_contacts: int  # grid-face safety walls touched (0: the grid held)
    grid_moves: int  # times the grid moved under a body that left the planned region
    ballistic_frames: int
    reason: str  # why the planner chose the mode
    finite: bool
    seconds: dict[str, float]  # plan, simulate, render, write


@dataclass
class RunResult:
    """What ``run_pipeline`` did: report.json's contents and the futures it simulated."""

    report: dict  # report.json's contents
    futures: list[FutureResult]  # "mean" first


def run(cfg) -> dict:
    """Hydra entry (simulate.py): user errors print ``error: ...`` and exit with code 2."""
    try:
        run_cfg = from_hydra(cfg)
        result = run_pipeline(run_cfg)
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    asked = _planner(run_cfg).cells_across
    from physgm.pipeline.standing import describe as describe_base  # torch is loaded by now

    if (note := describe_base(result.report["object"]["base"])) is not None:
        print(f"note: {note}")
    for r in result.futures:
        print(
            f"{run_cfg.output_dir / r.video}: {r.material} E={r.E:.3g} Pa nu={r.nu:.2f}, "
            f"{r.mode} ({r.predicted_error_px:.2f} px predicted error)"
        )
        if r.face_contacts:
            print(f"warning: {r.video}: {wall_warning(r.face_contacts)}", file=sys.stderr)
        if _coarse(r, asked):
            print(f"warning: {r.video}: {coarse_warning(r.cells_across, asked)}", file=sys.stderr)
    print(
        f"done in {result.report['seconds']['total']:.1f} s; contact sheet: "
        f"{run_cfg.output_dir / 'contact_sheet.png'}, report: {run_cfg.output_dir / 'report.json'}"
    )
    return result.report


# A grid with fewer than this share of the planner's cells across the object is reported: its clip
# is the grid's more than the material's (docs/measurements_sim.md section 39).
COARSE_SHARE = 0.5


def _coarse(r: FutureResult, asked: int) -> bool:
    """Was this future simulated on a grid under ``COARSE_SHARE`` of the ``asked`` cells across?"""
    return r.mode != "rigid" and r.cells_across < COARSE_SHARE * asked


def coarse_warning(cells: float, asked: int) -> str:
    """What to tell a user whose object was simulated on a grid much coarser than it asks for."""
    return (
        f"the object was simulated with {cells:.1f} grid cells across it, where planner.cells_across={asked} "
        "asks for more: the region it can reach (a long fall, a granular runout, a push) did not fit "
        "planner.max_cells cells per axis at the finer cell, so its deformation is the coarse grid's. "
        "A finer clip at more cost: raise planner.max_cells (default 96)."
    )


def wall_warning(face_contacts: int) -> str:
    """What to tell a user whose object reached the edge of the simulated region."""
    return (
        f"the object reached the edge of the simulated region ({face_contacts} grid-node updates stopped "
        "there): it rolled, bounced or slid further than the planner allowed for, and from there on the "
        "clip shows it held by an invisible wall. A wider region: planner.spread_factor=2 (default 0.5, "
        "in object sizes), at a small cost per sub-step. (The grid follows the body by itself with "
        "planner.follow=true, in scenes without velocity boxes, side walls or periodic axes.)"
    )


def _load_model(cfg: RunConfig):
    """The model and what report.json records about its checkpoint (with the input size it reads)."""
    from physgm.model.checkpoint import input_size, load_model

    model, ckpt = load_model(cfg.ckpt, cfg.device)
    return model, {**ckpt.summary(), "input_size": input_size(model, ckpt.hparams)}


def _predict(model, inp):
    """The model's Gaussians (valid pixels only, CPU), physics posterior (CPU) and domain gate for
    one scene (``physgm.model.predict.ScenePrediction``)."""
    import torch

    from physgm.model.predict import predict_scene

    pred = predict_scene(model, inp.images, inp.masks, inp.c2w, inp.Ks, inp.classifier_images)
    g, post = pred.gaussians, pred.posterior
    if len(g) == 0:
        raise UserError("the model placed no Gaussian inside the object mask; check the mask (mask.png)")
    values = [g.means, g.scales, g.opacities, g.colors, post.material_logits, post.z_E_mean, post.z_nu_mean]
    if not all(bool(torch.isfinite(v).all()) for v in values):
        raise UserError(
            "the model produced non-finite values for this input; the checkpoint is probably broken (NaN "
            "weights)"
        )
    return pred


def _planner(cfg: RunConfig):
    """The run's ``PlannerConfig``; a mistyped setting stops the run with what was wrong."""
    from physgm.sim.planner import PlannerConfig

    try:
        return PlannerConfig(**cfg.planner)
    except (TypeError, ValueError) as err:
        raise UserError(f"bad planner settings: {err}") from None


# MPM particle-substeps a second at which the time guard predicts a run: faster than any CPU run
# measured here (14.1 M at best, on a 2-core AVX-512 host: docs/measurements_sim.md section 27), so what it
# refuses is sure to take longer than the limit.
GUARD_THROUGHPUT = 1.5e7


def _prepare(g, choice, cfg: RunConfig, planner, camera, overrides: dict):
    """Particles, scene and plan of one future (``prepare_simulation``), before any solver step."""
    from physgm.sim.gaussian_trajectory import prepare_simulation
    from physgm.sim.mpm.stepping import SolverConfig

    try:
        solver = replace(SolverConfig.from_dict(cfg.solver), frame_dt=1.0 / cfg.output.fps)
    except (TypeError, ValueError) as err:
        raise UserError(f"bad solver settings: {err}") from None
    try:
        return prepare_simulation(
            g,
            choice.spec(),
            cfg.scene,
            camera,
            n_frames=cfg.output.frames,
            planner=planner,
            solver=solver,
            scene_overrides=overrides or None,
        )
    except ValueError as err:
        raise _cannot_simulate(choice, cfg, err) from None


def _cannot_simulate(choice, cfg: RunConfig, err: ValueError) -> UserError:
    """The simulator validates materials and scenes with ValueError, when it plans or when it
    builds the solver (an integrator that refuses a model): the user's error, with the run named."""
    return UserError(f"cannot simulate {choice.label()} in scene {cfg.scene!r}: {err}")


def check_time(futures: list, cfg: RunConfig) -> None:
    """Stop before simulating when the plans (``futures``: (choice, prepared) pairs) predict more
    than ``max_sim_minutes`` on a CPU even at ``GUARD_THROUGHPUT``: an explicit step follows the
    material's wave speed, and a stiff body a scene forces to deform (a metal bar drawn 30 % by
    the stretch's grips, at steel's stiffness) takes hours."""
    limit = cfg.max_sim_minutes
    if limit is None or cfg.device != "cpu":  # no throughput is known for CUDA here
        return
    seconds = [prepared.predicted_seconds(GUARD_THROUGHPUT) for _, prepared in futures]
    total = sum(seconds)
    if total <= 60.0 * limit:
        return
    choice, prepared = futures[seconds.index(max(seconds))]
    plan = prepared.plan
    took = f"{total / 60:.0f} minutes" if total < 5400 else f"{total / 3600:.1f} hours"
    raise UserError(
        f"the simulation would take {took} or more, over max_sim_minutes={limit:g} "
        f"({choice.label()}: {plan.mode} at E={plan.E_used:.3g} Pa, {plan.substeps_per_frame:,} sub-steps a "
        f"frame for {len(prepared.sample):,} particles, predicted at {GUARD_THROUGHPUT / 1e6:.0f} M "
        f"particle-substeps/s, faster than any CPU measured). The explicit step shrinks as 1 / sqrt(E): "
        f"a lower physics.E or a softer physics.material takes fewer; max_sim_minutes=null runs it anyway"
    )


def _simulate(prepared, choice, cfg: RunConfig):
    """Run one prepared future, with a progress bar of the clip's frames."""
    from tqdm import tqdm

    from physgm.sim.gaussian_trajectory import run_prepared
    from physgm.sim.mpm.stepping import SimulationDiverged

    # The simulation is most of what a user waits for (minutes for stiff rubbery bodies): a bar of
    # the clip's frames, with the sub-steps they took.
    plan = prepared.plan
    desc = f"{choice.name}: simulating ({plan.mode}, {len(prepared.sample.x):,} particles)"
    with tqdm(
        total=plan.n_frames, desc=desc, unit="frame", disable=not cfg.output.progress, leave=False
    ) as bar:

        def on_frame(frames: int, substeps: int) -> None:
            bar.set_postfix_str(f"{substeps:,} sub-steps", refresh=False)
            bar.update(frames - bar.n)

        try:
            traj = run_prepared(prepared, cfg.device, on_frame=on_frame)
        except ValueError as err:
            raise _cannot_simulate(choice, cfg, err) from None
        except SimulationDiverged as err:  # the guard gave up after its retries; nothing was written
            raise UserError(
                f"the simulation of {choice.label()} in scene {cfg.scene!r} failed: {err} Here: "
                "solver.cfl=0.2 halves the step, planner.cells_across=16 refines the grid"
            ) from None
    plan_s = float(traj.plan_seconds)  # particle sampling + planning, inside traj.seconds
    return traj, plan_s, max(0.0, traj.seconds - plan_s)


def _future_result(choice, traj, seconds: dict, finite: bool, video: str) -> FutureResult:
    plan = traj.plan
    return FutureResult(
        name=choice.name,
        material=choice.material,
        E=choice.E,
        nu=choice.nu,
        particles=int(len(traj.particles.x)),
        mode=plan.mode,
        integrator=plan.integrator,
        predicted_error_px=plan.predicted_error_px,
        error_terms={k: round(float(v), 4) for k, v in plan.error_terms.items()},
        px_per_m=round(float(plan.px_per_m), 2),
        E_used=plan.E_used,
        nu_used=plan.nu_used,
        dx_m=plan.dx,
        cells_across=round(float(plan.cells_across), 2),
        grid_cells=plan.summary()["grid_cells"],
        reason=plan.reason,
        substeps=int(traj.substeps),
        rest_frame=traj.rest_frame,
        face_contacts=int(traj.face_contacts),
        grid_moves=int(traj.grid_moves),
        ballistic_frames=traj.ballistic_frames,
        seconds={k: round(v, 3) for k, v in seconds.items()},
        video=video,
        finite=finite,
    )


def run_pipeline(cfg: RunConfig) -> RunResult:
    """Run the whole pipeline into ``cfg.output_dir`` (atomically)."""
    import torch

    threads = torch.get_num_threads()
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)
    try:
        return _execute(cfg)
    finally:
        torch.set_num_threads(threads)


def _execute(cfg: RunConfig) -> RunResult:
    from hydra.utils import instantiate

    from physgm.pipeline.physics_choice import choose_physics, physics_json
    from physgm.pipeline.prepared_input import input_kind, prepare_input
    from physgm.pipeline.staging import (
        box_in_view,
        clip_region,
        direction,
        floor_image,
        framing_camera,
        motion_region,
        opaque_bounds,
        place_object,
    )
    from physgm.pipeline.standing import stand_on_base
    from physgm.render.frames import Shot, render_trajectory
    from physgm.sim.sampling import mass_opacity
    from physgm.view.sequence import sequence_file, sequence_from_trajectory

    start = time.perf_counter()
    sec = dict.fromkeys(STAGES, 0.0)
    folder = RunFolder(cfg.output_dir)  # fails early on a non-empty or unwritable output folder
    with folder as tmp:
        # -- load ---------------------------------------------------------------------------
        t0 = time.perf_counter()
        kind = input_kind(cfg.input)
        scene = scene_settings(cfg)  # a mistyped scene setting stops the run before the model loads
        planner = _planner(cfg)  # and so does a planner setting
        model, ckpt_info = (None, None) if kind == "ply" else _load_model(cfg)
        inp = prepare_input(cfg.input, None if model is None else ckpt_info["input_size"], cfg.mask, cfg.up)
        sec["load"] = time.perf_counter() - t0
        # -- model + physics choice + placement -------------------------------------------------
        t0 = time.perf_counter()
        pred = _predict(model, inp) if model is not None else None
        g, post = (pred.gaussians, pred.posterior) if pred is not None else (inp.gaussians, None)
        runs = choose_physics(post, cfg.physics, cfg.seed)
        min_opacity = mass_opacity(g.opacities, planner.min_opacity, planner.relative_opacity)
        ground = scene.ground_height
        placement = place_object(g, cfg.size_m, ground or 0.0, min_opacity)
        base = None
        if cfg.stand and kind != "ply" and ground is not None:
            friction = float(scene.settings["ground"].get("friction", 0.0))
            placement, base = stand_on_base(placement, min_opacity, ground, friction, planner)
        az = inp.azimuth_deg if cfg.camera.azimuth_deg is None else cfg.camera.azimuth_deg
        el = inp.elevation_deg if cfg.camera.elevation_deg is None else cfg.camera.elevation_deg
        rest_lo, rest_hi = opaque_bounds(placement.gaussians, min_opacity)
        scene = scene.facing(direction(az, el), rest_hi - rest_lo)
        lo, hi = motion_region(rest_lo, rest_hi, cfg.scene, scene.settings)
        res = cfg.output.resolution
        # The planner measures its pixel errors in this camera, framed on the planned motion.
        camera = framing_camera(lo, hi, az, el, cfg.camera.fov_deg, res, res, cfg.camera.margin)
        sec["model"] = time.perf_counter() - t0
        # -- per future: plan and simulate ---------------------------------------------------
        futures = [
            (choice, _prepare(placement.gaussians, choice, cfg, planner, camera, scene.overrides))
            for choice in runs
        ]
        check_time(futures, cfg)  # every plan first: a run too long to wait for stops before any
        sims = []
        for choice, prepared in futures:
            sims.append((choice, *_simulate(prepared, choice, cfg)))
        # -- the output camera: the planned region, grown to what the runs did -----------------
        t0 = time.perf_counter()
        view_lo, view_hi = clip_region(lo, hi, [traj.x for _, traj, _, _ in sims])
        # A body that left the planned region, and the frame with it: widen the camera (never narrow
        # it, so every error the planner bounded is as small or smaller in the clip).
        reframed = not box_in_view(camera, view_lo, view_hi)
        planning_camera = camera
        if reframed:
            camera = framing_camera(view_lo, view_hi, az, el, cfg.camera.fov_deg, res, res, cfg.camera.margin)
        bg = np.broadcast_to(np.asarray(cfg.output.background, np.float32), (res, res, 3)).copy()
        if cfg.output.floor and ground is not None:
            bg = floor_image(camera, ground, cfg.size_m / 4, np.asarray(cfg.output.background))
        shot = Shot(
            camera, instantiate({"_target_": "physgm.render.Renderer", **cfg.renderer}), bg, cfg.device
        )
        frame_s = time.perf_counter() - t0
        # -- per future: render, write the video ---------------------------------------------
        results, videos, sheet_rows, rest_state = [], {}, [], None
        for choice, traj, plan_s, sim_s in sims:
            t0 = time.perf_counter()
            desc = f"{choice.name} ({traj.plan.mode})"
            frames, finite = render_trajectory(traj, shot, cfg.output.progress, desc)
            finite = finite and bool(np.isfinite(traj.x).all() and np.isfinite(traj.F).all())
            render_s = time.perf_counter() - t0 + frame_s / len(sims)
            if not finite:
                raise RuntimeError(
                    f"run {choice.label()} produced non-finite positions or pixels; nothing was written"
                )
            t0 = time.perf_counter()
            video = "video.mp4" if choice.name == "mean" else f"video_{choice.name}.mp4"
            write_mp4(tmp / video, frames, cfg.output.fps)
            if cfg.output.frame_plys:
                write_frame_plys(traj, tmp / ("frames" if choice.name == "mean" else f"frames_{choice.name}"))
            # what ``python -m physgm.view RUN_DIR`` shows: the moving Gaussians, beside the video
            sequence_from_trajectory(traj, camera, cfg.output.fps, ground).save(
                tmp / sequence_file(choice.name)
            )
            if cfg.output.gif:
                write_gif(tmp / video.replace(".mp4", ".gif"), frames, cfg.output.fps)
            write_s = time.perf_counter() - t0
            if rest_state is None:
                rest_state = traj.gaussians_at(0)
            videos[choice.name] = video
            sheet_rows.append((choice.name, frames, keyframe_indices(len(frames), cfg.output.keyframes)))
            stage = {"plan": plan_s, "simulate": sim_s, "render": render_s, "write": write_s}
            for k, v in stage.items():
                sec[k] += v
            results.append(_future_result(choice, traj, stage, finite, video))
        # -- write the rest ------------------------------------------------------------------
        t0 = time.perf_counter()
        from physgm.gaussians import write_ply

        write_ply(rest_state, tmp / "gaussians.ply")
        if inp.kind == "ply":  # no photo to show: the object as the first frame shows it
            inp.preview = shot.draw(rest_state).clip(0, 1)
        else:
            save_png(tmp / "mask.png", inp.mask_image)
            save_png(tmp / "input.png", inp.preview)
        phys = physics_json(post, cfg.physics, runs, videos, None if pred is None else pred.domain_real)
        write_json(tmp / "physics.json", phys)
        lines = _sheet_lines(phys, results, cfg)
        save_png(tmp / "contact_sheet.png", contact_sheet(inp.preview, sheet_rows, lines, cfg.output.fps))
        write_json(tmp / "config.json", _plain_config(cfg))
        sec["write"] += time.perf_counter() - t0
        sec["total"] = time.perf_counter() - start
        report = plain_json(
            _report(
                cfg,
                inp,
                ckpt_info,
                scene.settings,
                placement,
                camera,
                planning_camera,
                reframed,
                az,
                el,
                sec,
                results,
                g,
                min_opacity,
                base,
            )
        )
        write_json(tmp / "report.json", report)
        folder.commit()
    return RunResult(report, results)


def _sheet_lines(phys: dict, results: list[FutureResult], cfg: RunConfig) -> list[str]:
    lines = [f"scene: {cfg.scene}, object {cfg.size_m:g} m"]
    post = phys["posterior"]
    if post is not None:
        lines.append("predicted material:")
        lines += [f"  {name} {p:.2f}" for name, p in post["material_top3"]]
        e = post["E_Pa"]
        lines.append(f"predicted E: {e['mean']:.3g} Pa [{e['low_1sigma']:.2g}, {e['high_1sigma']:.2g}]")
        lines.append(f"predicted nu: {post['nu']['mean']:.3f} +- {post['nu']['std']:.3f}")
        if post.get("domain_real") is not None:
            lines.append(f"looks real: {post['domain_real']:.2f} (domain gate)")
    else:
        lines.append("no prediction (.ply input)")
    lines.append("simulated:")
    asked = _planner(cfg).cells_across
    for r in results:
        lines.append(f"  {r.name}: {r.material} E={r.E:.3g} nu={r.nu:.2f}")
        if (r.E_used, r.nu_used) != (r.E, r.nu):  # a cap the planner took, counted in the error
            lines.append(f"    run as E={r.E_used:.3g} nu={r.nu_used:.2f}")
        lines.append(f"    {r.mode}, error {r.predicted_error_px:.2f} px, {r.substeps} steps")
        if r.face_contacts:
            lines.append("    held by the region's edge (see the warning)")
        if _coarse(r, asked):
            lines.append(f"    on a coarse grid, {r.cells_across:.1f} cells across (see the warning)")
    return lines


def _plain_config(cfg: RunConfig) -> dict:
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()}


def _report(
    cfg, inp, ckpt_info, scene_cfg, placement, camera, planning_camera, reframed, az, el, sec, results, g,
    min_opacity, base,
) -> dict:  # fmt: skip
    from physgm.sim.planner.deformation import pixels_per_metre

    mean = results[0]
    eye = camera.c2w[0, :3, 3].double().numpy()
    rest = placement.gaussians.means[placement.gaussians.opacities >= min_opacity]
    return {
        "input": {"kind": inp.kind, **inp.info},
        "checkpoint": ckpt_info,
        "scene": cfg.scene,
        "scene_settings": scene_cfg,
        "device": cfg.device,
        "torch_threads": cfg.torch_threads,
        "output": {
            "resolution": cfg.output.resolution,
            "frames": cfg.output.frames,
            "fps": cfg.output.fps,
            "videos": [r.video for r in results],
        },
        "object": {
            "size_m": cfg.size_m,
            "m_per_model_unit": placement.scale,
            "gaussians": len(g),
            # the opacity from which a Gaussian carries mass (sampling.mass_opacity), and how many do
            "mass_opacity": min_opacity,
            "gaussians_with_mass": int((g.opacities >= min_opacity).sum()),
            "object_to_world": placement.object_to_world,
            # the underside cut flat so the object stands (pipeline/standing.py; null: not tested)
            "base": None if base is None else base.as_dict(),
        },
        "camera": {
            "azimuth_deg": az,
            "elevation_deg": el,
            "fov_deg": cfg.camera.fov_deg,
            "eye_m": eye,
            # True: a run left the planned motion region and the camera was moved back to show it
            # (``staging.clip_region``); the runs' px_per_m and pixel errors are the planning camera's
            "reframed": reframed,
            # the object at rest, px per m, in this camera and in the one the planner measured in
            "px_per_m": pixels_per_metre(camera, rest),
            "px_per_m_planned": pixels_per_metre(planning_camera, rest),
        },
        "seconds": {k: round(v, 3) for k, v in sec.items()},
        "mode": mean.mode,
        "predicted_error_px": mean.predicted_error_px,
        "particles": mean.particles,
        "grid_cells": mean.grid_cells,
        "substeps": mean.substeps,
        "finite": all(r.finite for r in results),
        "runs": [asdict(r) for r in results],
        "stage_notes": "load = input + checkpoint; model = forward pass, physics choice, placement; "
        "plan/simulate = physgm.sim.gaussian_trajectory.simulate; render = deforming + rasterising per "
        "frame; write = videos, Gaussians over time, PLYs, images, JSON",
    }
