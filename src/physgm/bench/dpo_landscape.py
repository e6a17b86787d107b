"""``python -m physgm.bench dpo-landscape``: the DPO trajectory distance as a function of Young's modulus.

DPO (stage 2) ranks physics candidates by the trajectory distance between their simulated clip
and the scene's reference video; it can only recover E if that distance is lowest near the true
E. For each selected scene and Gaussian source this sweeps E = true E x 10^d over a grid of
decades d, with the TRUE material and nu, and scores each clip exactly as the rollouts do:

- ``true``: the asset's own ``gaussians.ply`` (the Gaussians the reference video was made
  from), with the asset's density: at d = 0 this re-creates the reference simulation;
- ``predicted``: the model's Gaussians as the rollout callback uses them (``rollout_env.predict``),
  with the material table's density, as ``rollout_env.physics_spec`` hands it to the simulator.

Each point holds three numbers against the decoded H.264 reference: ``distance``, the paper's
track distance of the raw rendered clip (what the rollouts scored before
``SimSettings.codec_round_trip``); ``distance_encoded``, the same of the clip passed through the
same encoding first, so codec noise in the tracks and landing frames cancels; and ``score``, the
rollouts' clip score (``physgm.metrics.clip_score``: tracks + edge profile + silhouette, on the
encoded clip), with its ``terms``. A landscape whose spread is
under ``--min-gap`` (the rollouts' tie threshold) is "flat": DPO gets no pair from it and its
argmin is reported as null. DPO only compares candidates drawn near the policy's current mean,
so each predicted landscape also reports ``policy_d`` (the model's mean log10 E minus the true
one) and ``slope_toward_truth``: the distance at the grid point nearest ``policy_d`` minus the
distance one grid step closer to the truth (> 0: a local comparison there points the right way).
One JSON object goes to stdout, progress lines to stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from physgm.gaussians import Gaussians
from physgm.physics.materials import PhysicsSpec

DEFAULT_MATERIALS = ("metal", "jelly", "plasticine", "snow", "sand")
DEFAULT_DECADES = tuple(np.round(np.arange(-2.0, 2.01, 0.5), 2).tolist())
SOURCES = ("true", "predicted")
NEAR_DECADES = 0.5  # an argmin within this many decades of the truth counts as recovered
QUARTER = 0.25  # the stricter test: the minimum within a quarter decade of the truth
KEYS = ("distance", "distance_encoded", "score")


@dataclass
class LandscapePoint:
    """One simulated E of one scene and Gaussian source."""

    d: float  # decades from the true E: E = true E x 10^d
    log10_E: float
    distance: float | None  # DPO trajectory distance (None: the run failed or the tracker lost the object)
    distance_encoded: float | None  # the clip through the reference's H.264 encoding first
    score: float | None  # the rollouts' clip score of the encoded clip (physgm.metrics.clip_score)
    mode: str  # planner path: rigid / mpm
    E_used: float | None  # Pa, after the planner's stiffness cap
    landing_reference: int | None  # landing frames the metric aligned (raw clip)
    landing_candidate: int | None
    seconds: float
    error: str | None = None
    terms: dict | None = None  # the score's parts


def sweep(
    scene,
    gaussians: Gaussians,
    physics: PhysicsSpec,
    decades: list[float],
    reference: np.ndarray,
    settings,
    device: str = "cpu",
    log=None,
) -> list[LandscapePoint]:
    """Simulate ``physics`` with E = physics.E x 10^d for each d; score each clip against ``reference``."""
    from physgm.data.video import codec_round_trip
    from physgm.metrics.clip_score import score_clip
    from physgm.metrics.trajectory import score_videos
    from physgm.train.rollout_env import simulate_clip

    points = []
    for d in decades:
        E = float(physics.E) * 10.0**d
        start = time.perf_counter()
        point = LandscapePoint(d, math.log10(E), None, None, None, "", None, None, None, 0.0)
        try:
            frames, run = simulate_clip(
                scene, gaussians, replace(physics, E=E), settings, len(reference), device
            )
            if frames is None:
                raise RuntimeError(run.skipped)
            raw = score_videos(reference, frames)
            encoded = codec_round_trip(frames, scene.fps)
            enc = score_videos(reference, encoded)
            clip = score_clip(reference, encoded, settings.score)
            point.distance = _finite(raw.distance)
            point.distance_encoded = _finite(enc.distance)
            point.score, point.terms = _finite(clip.value), clip.terms
            point.landing_reference, point.landing_candidate = raw.landing_reference, raw.landing_candidate
            point.mode, point.E_used = str(run.trajectory.plan.mode), float(run.trajectory.plan.E_used)
            if point.distance is None:
                point.error = "trajectory distance is not finite (object lost by the tracker)"
        except (ValueError, RuntimeError) as err:  # as the rollouts: a diverged or unsimulable candidate
            point.error = f"{type(err).__name__}: {err}"
        point.seconds = round(time.perf_counter() - start, 2)
        points.append(point)
        if log:
            log(
                f"  d={d:+.2f} distance={point.distance} encoded={point.distance_encoded} "
                f"score={point.score} {point.mode} "
                f"{point.seconds}s" + (f" error={point.error}" if point.error else "")
            )
    return points


def shape(points: list[LandscapePoint], key: str, min_gap: float, policy_d: float | None = None) -> dict:
    """Argmin d, spread, the basin (every d DPO could not tell from the best) and the slope at the policy."""
    ok = sorted((p.d, getattr(p, key)) for p in points if getattr(p, key) is not None)
    if not ok:
        return {
            "argmin_d": None,
            "spread": None,
            "flat": None,
            "basin_d": [],
            "at_truth": None,
            "slope_toward_truth": None,
        }
    ds, dist = np.array([d for d, _ in ok]), np.array([v for _, v in ok])
    spread = float(dist.max() - dist.min())
    flat = spread < min_gap
    at_truth = next((v for d, v in ok if abs(d) < 1e-9), None)
    slope = None
    if policy_d is not None and len(ds) > 1:
        i = int(np.argmin(np.abs(ds - policy_d)))
        j = i - 1 if ds[i] > 0 else i + 1  # one grid step towards d = 0
        if abs(ds[i]) > 1e-9 and 0 <= j < len(ds):
            slope = float(dist[i] - dist[j])
    return {
        "argmin_d": None if flat else float(ds[int(np.argmin(dist))]),
        "spread": spread,
        "flat": bool(flat),
        "basin_d": [float(d) for d in ds[dist - dist.min() < min_gap]],
        "at_truth": at_truth,
        "slope_toward_truth": slope,
    }


def summarise(rows: list[dict], sources: list[str]) -> dict:
    """Per material and source: median |argmin d| (and signed), median spread, share within 0.5 decade."""
    out = {}
    for material in dict.fromkeys(r["material"] for r in rows):
        subset = [r for r in rows if r["material"] == material]
        out[material] = {}
        for source in sources:
            entry = {"n": len(subset)}
            policy = [r["sources"][source].get("policy_d") for r in subset]
            if any(v is not None for v in policy):
                entry["median_policy_d"] = float(np.median([v for v in policy if v is not None]))
            for key in KEYS:
                shapes = [r["sources"][source][key] for r in subset]
                signed = [s["argmin_d"] for s in shapes if s["argmin_d"] is not None]
                argmins = [abs(d) for d in signed]
                spreads = [s["spread"] for s in shapes if s["spread"] is not None]
                truth = [s["at_truth"] for s in shapes if s["at_truth"] is not None]
                entry[key] = {
                    "median_abs_argmin_d": float(np.median(argmins)) if argmins else None,
                    "median_argmin_d": float(np.median(signed)) if signed else None,  # > 0: prefers too stiff
                    "median_spread": float(np.median(spreads)) if spreads else None,
                    "within_0.5": sum(a <= NEAR_DECADES + 1e-9 for a in argmins) / len(subset),
                    "within_0.25": sum(a <= QUARTER + 1e-9 for a in argmins) / len(subset),
                    "flat": sum(bool(s["flat"]) for s in shapes),
                    "median_at_truth": float(np.median(truth)) if truth else None,
                }
                slopes = [s["slope_toward_truth"] for s in shapes if s.get("slope_toward_truth") is not None]
                if (
                    slopes
                ):  # predicted source: does a step from the policy's E towards the truth lower the distance?
                    entry[key]["toward_truth_at_policy"] = sum(v > 0 for v in slopes) / len(slopes)
            out[material][source] = entry
    return out


def select_scenes(
    data: str,
    splits: list[str],
    materials: list[str],
    per_material: int,
    input_resolution: int | None,
    num_views: int,
    background: float,
    seed: int,
    skip: int = 0,
) -> list:
    """``per_material`` scenes of each material, in split order, after skipping the first ``skip``."""
    from physgm.train.rollout_env import load_scenes

    chosen, count = [], {m: -skip for m in materials}
    for split in splits:
        for scene in load_scenes(data, split, "drop", num_views, input_resolution, background, seed):
            if count.get(scene.material, per_material) < per_material and scene.true_known:
                if count[scene.material] >= 0:
                    chosen.append(scene)
                count[scene.material] += 1
    missing = {m: per_material - max(c, 0) for m, c in count.items() if c < per_material}
    if missing:
        print(
            f"dpo-landscape: fewer scenes than asked for {missing} (splits {splits} of {data})",
            file=sys.stderr,
        )
    return sorted(chosen, key=lambda s: (materials.index(s.material), s.id))


def source_gaussians(source: str, scene, data: str, model) -> tuple[Gaussians, str, float | None]:
    """The Gaussians of ``source`` for a scene, the density that goes with them by default, and the
    policy's mean log10 E minus the true one (predicted source only)."""
    if source == "true":
        from physgm.gaussians import read_ply

        return read_ply(Path(data) / scene.id / "gaussians.ply", keep_sh=False), "asset", None
    from physgm.train.rollout_env import predict

    gaussians, posterior = predict(model, scene.inputs)
    return gaussians, "table", float(posterior.log10_E_mean[0]) - scene.log10_E


def physics_for(scene, data: str, density: str) -> PhysicsSpec:
    """True material, E and nu, with the asset's density ("asset") or the material table's ("table")."""
    from physgm.data.format import load_asset
    from physgm.physics.materials import get_material

    if density == "asset":
        rho = load_asset(Path(data) / scene.id).physical.density
        if rho is None:
            raise ValueError(f"{scene.id}/physical.json has no density; run with --density table")
    else:  # what rollout_env.physics_spec gives the simulator: no density, the table's is used
        rho = get_material(scene.material).density
    E, nu = float(10.0**scene.log10_E), float(scene.nu)
    return PhysicsSpec(str(scene.material), E=E, nu=nu, density=float(rho))


def parse_decades(values: list[str]) -> list[float]:
    """``--decades -1 0 1``, ``--decades=-1,0,1`` or a mix, as floats."""
    try:
        return [float(v) for text in values for v in text.split(",") if v.strip()]
    except ValueError:
        raise SystemExit(
            f"--decades takes numbers like -2 -1 0 1 2 (or --decades=-2,-1,0,1,2); got {values}"
        ) from None


def main(argv: list[str] | None = None) -> dict:
    from physgm.train.evaluate_dpo import input_settings
    from physgm.train.rollout_env import SimSettings, reference_frames

    p = argparse.ArgumentParser(
        prog="python -m physgm.bench dpo-landscape", description=__doc__.split("\n")[0]
    )
    p.add_argument("--data", default="data/dpo_eval_tiny", help="PhysAssets root with reference drop videos")
    p.add_argument("--ckpt", default="checkpoints/physgm_tiny.ckpt", help="model for --gaussians predicted")
    p.add_argument("--splits", default="dpo,test", help="splits to take scenes from, comma-separated")
    p.add_argument("--scenes", type=int, default=2, help="scenes per material")
    p.add_argument("--skip", type=int, default=0, help="skip the first N scenes of each material")
    p.add_argument("--materials", nargs="+", default=list(DEFAULT_MATERIALS))
    p.add_argument(
        "--decades", nargs="+", default=[str(d) for d in DEFAULT_DECADES], help="d values, E = true E x 10^d"
    )
    p.add_argument("--gaussians", choices=(*SOURCES, "both"), default="both")
    p.add_argument(
        "--density",
        choices=("auto", "asset", "table"),
        default="auto",
        help="auto: the asset's for true Gaussians (re-creates the reference), "
        "the table's for predicted (as DPO)",
    )
    p.add_argument(
        "--resolution", type=int, default=SimSettings.resolution, help="render size, px (rollout default)"
    )
    p.add_argument(
        "--frames", type=int, default=SimSettings.n_frames, help="frames compared (rollout default)"
    )
    p.add_argument(
        "--min-gap", type=float, default=0.002, help="distance gap under which DPO calls two candidates a tie"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the fixed input views (as the rollouts)")
    a = p.parse_args(argv)
    sources = list(SOURCES) if a.gaussians == "both" else [a.gaussians]
    a.decades = parse_decades(a.decades)
    if not a.decades:
        raise SystemExit("--decades is empty; give at least one value, e.g. -1,0,1")

    import warp as wp

    wp.config.quiet = True
    torch.set_num_threads(1)  # one worker: the machine is shared, rollouts here run one at a time
    start = time.perf_counter()
    model, inputs = None, {"input_resolution": None, "num_views": 4, "background": 1.0}
    if "predicted" in sources:
        from physgm.model.checkpoint import load_model

        model, ckpt = load_model(a.ckpt)
        inputs = input_settings(ckpt.hparams, model)
    scenes = select_scenes(
        a.data,
        [s.strip() for s in a.splits.split(",")],
        a.materials,
        a.scenes,
        inputs["input_resolution"],
        int(inputs["num_views"]),
        float(inputs["background"]),
        a.seed,
        a.skip,
    )
    # No time budget: a landscape is measured at the asked E, never with a cheaper plan.
    settings = SimSettings(
        resolution=a.resolution, n_frames=a.frames, device="cpu", budget={"max_seconds": None}
    )

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    rows = []
    for i, scene in enumerate(scenes):
        reference = reference_frames(scene, settings.n_frames)
        row = {**scene.truth(), "sources": {}}
        for source in sources:
            gaussians, default_density, policy_d = source_gaussians(source, scene, a.data, model)
            physics = physics_for(scene, a.data, default_density if a.density == "auto" else a.density)
            log(
                f"[{i + 1}/{len(scenes)}] {scene.id} {scene.material} log10E={scene.log10_E:.2f} {source} "
                f"({len(gaussians)} Gaussians, density {physics.density:.0f} kg/m^3, policy_d={policy_d})"
            )
            points = sweep(scene, gaussians, physics, a.decades, reference, settings, log=log)
            row["sources"][source] = {
                "gaussians": len(gaussians),
                "density": physics.density,
                "policy_d": policy_d,
                "points": [asdict(pt) for pt in points],
                **{key: shape(points, key, a.min_gap, policy_d) for key in KEYS},
            }
        rows.append(row)
    report = {
        "data": a.data,
        "ckpt": a.ckpt if model is not None else None,
        "decades": a.decades,
        "sources": sources,
        "settings": {
            "resolution": a.resolution,
            "frames": a.frames,
            "min_gap": a.min_gap,
            "density": a.density,
            "input": inputs,
            "torch_threads": 1,
        },
        "scenes": rows,
        "summary": summarise(rows, sources),
        "seconds": round(time.perf_counter() - start, 1),
    }
    print(json.dumps(report))
    return report


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None
