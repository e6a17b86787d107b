"""Pretrain-only vs DPO on held-out scenes with reference videos.

    python -m physgm.train.evaluate_dpo --pretrain STAGE1.ckpt --dpo DPO.ckpt --data ROOT [--split test]

For every scene of the split that has ``videos/drop.mp4``, each model predicts Gaussians and a
physics posterior from the scene's input views; the posterior MEAN physics (most likely
material, mean log10 E, mean nu) is simulated on the model's own Gaussians exactly like the
reference video was made, rendered from its camera and scored with the trajectory distance.
Reported per true material and overall: mean trajectory distance and median |log10 E - true|
(plus material accuracy). One JSON object goes to stdout and a markdown table to ``--table``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

from physgm.model.checkpoint import load_model
from physgm.physics.materials import MATERIAL_NAMES
from physgm.train.rollout import (
    SimSettings,
    evaluate_physics,
    load_scenes,
    physics_dict,
    predict,
    reference_frames,
)
from physgm.warp_runtime import preload

KEY_MATERIALS = ("metal", "jelly", "plasticine", "snow", "sand")  # always reported, as in the paper


def input_settings(hparams: dict, model) -> dict:
    """Views the model was trained on: stored by the DPO stage in the checkpoint's
    ``hyper_parameters``, else the encoder's native size."""
    inputs = dict(hparams.get("inputs") or {})
    inputs.setdefault("input_resolution", model.config.backbone.encoder.img_size)
    inputs.setdefault("num_views", 4)
    inputs.setdefault("background", 1.0)
    return inputs


def evaluate_scene(models: dict, scene, settings: SimSettings, workers: int) -> dict:
    """Both models' mean-physics rollouts of one scene."""
    reference = reference_frames(scene, settings.n_frames)
    row = {
        "scene": scene.id,
        "material": scene.material,
        "log10_E": scene.log10_E,
        "nu": scene.nu,
        "true_known": scene.true_known,
    }

    def run(name: str) -> tuple[str, dict]:
        gaussians, posterior = predict(models[name], scene.inputs)
        mean = posterior.mean()
        physics = physics_dict(mean)
        out = {
            "material": physics["material"],
            "log10_E": float(mean.log10_E[0, 0]),
            "nu": float(mean.nu[0, 0]),
        }
        start = time.perf_counter()
        try:
            distance, info = evaluate_physics(scene, gaussians, physics, reference, settings)
            out.update(distance=float(distance) if math.isfinite(distance) else None, mode=info.get("mode"))
        except (ValueError, RuntimeError) as err:
            out.update(distance=None, error=f"{type(err).__name__}: {err}")
        out["seconds"] = round(time.perf_counter() - start, 2)
        out["abs_log10_E_error"] = abs(out["log10_E"] - scene.log10_E) if scene.true_known else None
        return name, out

    preload("cpu")  # no Warp module may load while the workers launch kernels
    with ThreadPoolExecutor(max(1, workers)) as pool:
        row.update(dict(pool.map(run, list(models))))
    return row


def summarise(rows: list[dict], names: list[str]) -> dict:
    """Per-material and overall metrics of each model, and the DPO gains."""
    present = sorted({r["material"] for r in rows}, key=MATERIAL_NAMES.index)
    groups = {
        m: [r for r in rows if r["material"] == m]
        for m in (*KEY_MATERIALS, *[p for p in present if p not in KEY_MATERIALS])
    }
    groups["overall"] = rows

    def stats(subset: list[dict], name: str) -> dict:
        dist = [r[name]["distance"] for r in subset if r[name]["distance"] is not None]
        err = [r[name]["abs_log10_E_error"] for r in subset if r[name]["abs_log10_E_error"] is not None]
        acc = [r[name]["material"] == r["material"] for r in subset]
        return {"n": len(subset), "failed": len(subset) - len(dist),
                "mean_distance": float(np.mean(dist)) if dist else None,
                "median_abs_log10_E_error": float(np.median(err)) if err else None,
                "material_accuracy": float(np.mean(acc)) if acc else None}

    out = {}
    for group, subset in groups.items():
        out[group] = {name: stats(subset, name) for name in names}
        if len(names) == 2:
            a, b = out[group][names[0]], out[group][names[1]]
            out[group]["gain"] = {k: (1.0 - b[k] / a[k]) if a[k] and b[k] is not None else None
                                  for k in ("mean_distance", "median_abs_log10_E_error")}
    return out


def markdown(summary: dict, names: list[str]) -> str:
    """The summary as a markdown table (one row per material, then overall)."""
    def fmt(x, pct=False):
        return "—" if x is None else f"{100 * x:+.1f}%" if pct else f"{x:.4f}"

    head = ["material", "n"] + [f"{n} dist" for n in names] + [f"{n} med abs dlog10E" for n in names]
    head += [f"{n} mat acc" for n in names] + ["dist gain", "E-err gain"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for group, s in summary.items():
        cells = [group, str(s[names[0]]["n"])]
        cells += [fmt(s[n]["mean_distance"]) for n in names] + [
            fmt(s[n]["median_abs_log10_E_error"]) for n in names
        ]
        cells += [fmt(s[n]["material_accuracy"]) for n in names]
        gain = s.get("gain", {})
        cells += [fmt(gain.get("mean_distance"), True), fmt(gain.get("median_abs_log10_E_error"), True)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m physgm.train.evaluate_dpo", description=__doc__.split("\n")[0]
    )
    p.add_argument("--pretrain", required=True, help="stage-1 checkpoint")
    p.add_argument("--dpo", required=True, help="stage-2 (DPO) checkpoint")
    p.add_argument("--data", required=True, help="PhysAssets root with splits/ and reference videos")
    p.add_argument(
        "--split",
        default="test",
        help="split(s) to evaluate, comma-separated (e.g. test,dpo of a held-out set)",
    )
    p.add_argument("--video", default="drop", help="reference video name (videos/<name>.mp4)")
    p.add_argument("--max-scenes", type=int, default=None)
    p.add_argument(
        "--views", type=int, default=None, help="input views (default: as in DPO training, else 4)"
    )
    p.add_argument(
        "--input-resolution", type=int, default=None, help="input view size, px (default: as in training)"
    )
    p.add_argument(
        "--resolution", type=int, default=None, help="render size, px (default: the reference video's)"
    )
    p.add_argument(
        "--frames", type=int, default=None, help="frames to compare (default: the whole reference video)"
    )
    p.add_argument(
        "--cells-across",
        type=int,
        default=None,
        help="MPM cells across the object (default: planner default)",
    )
    p.add_argument("--backend", default="warp")
    p.add_argument("--workers", type=int, default=2, help="models simulated at once (threads)")
    p.add_argument(
        "--seed", type=int, default=0, help="seed of the fixed evaluation views (as the datamodule)"
    )
    p.add_argument(
        "--table", type=Path, default=None, help="markdown output (default: next to the DPO checkpoint)"
    )
    a = p.parse_args(argv)

    torch.manual_seed(a.seed)
    pretrained, _ = load_model(a.pretrain)
    tuned, tuned_ckpt = load_model(a.dpo)
    models = {"pretrain": pretrained, "dpo": tuned}
    inputs = input_settings(tuned_ckpt.hparams, tuned)
    views = a.views or int(inputs["num_views"])
    res = a.input_resolution or inputs["input_resolution"]
    scenes = [s for split in a.split.split(",") for s in
              load_scenes(a.data, split.strip(), a.video, views, res, float(inputs["background"]), a.seed)]
    scenes = scenes[: a.max_scenes]
    settings = SimSettings(resolution=a.resolution, n_frames=a.frames, backend=a.backend,
                           planner={"cells_across": a.cells_across} if a.cells_across else {}, device="cpu")
    start = time.perf_counter()
    rows = []
    for i, scene in enumerate(scenes):
        rows.append(evaluate_scene(models, scene, settings, a.workers))
        print(f"[{i + 1}/{len(scenes)}] {scene.id} ({scene.material}): "
              + ", ".join(f"{n} d={rows[-1][n]['distance']}" for n in models), file=sys.stderr, flush=True)
    names = list(models)
    summary = summarise(rows, names)
    table = a.table or Path(a.dpo).resolve().parent / "evaluate_dpo.md"
    table.parent.mkdir(parents=True, exist_ok=True)
    table.write_text(markdown(summary, names))
    report = {"pretrain": a.pretrain, "dpo": a.dpo, "data": a.data, "split": a.split, "scenes": len(rows),
              "views": views, "input_resolution": res, "seconds": round(time.perf_counter() - start, 1),
              "settings": {"resolution": a.resolution, "frames": a.frames, "cells_across": a.cells_across},
              "summary": summary, "table": str(table), "per_scene": rows}
    print(json.dumps(report))
    print(markdown(summary, names), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
