"""Stage 1 against stage 2 (DPO) on held-out scenes with reference videos: the paper's DPO ablation.

    python -m physgm.train.evaluate_dpo --pretrain STAGE1.ckpt --dpo DPO.ckpt --data ROOT [--split test]

For every scene of the split that has ``videos/drop.mp4``, each model predicts Gaussians and a
physics posterior from the scene's input views; the posterior MEAN physics (most likely
material, mean log10 E, mean nu) is simulated on the model's own Gaussians exactly like the
reference video was made, rendered from its camera and compared with the reference. Reported
per true material (metal, jelly, plasticine, snow, sand, rubber always, then any other present)
and overall: mean trajectory distance (the paper's tracks recipe), mean rollout score (the score
DPO ranks by), a perceptual distance (``physgm.metrics.perceptual``), median |log10 E - true|
and material accuracy. One JSON object goes to stdout (and ``--out``/evaluate_dpo.json), the
table to stderr and ``--out``/evaluate_dpo.md, and one contact sheet per material (reference,
stage 1, stage 2) to ``--out``/sheet_<material>.png.

Each model's rollout of each scene is stored as it finishes (``--rollouts``, by default
``--out``/rollouts), keyed by the model's weights and the settings: a stopped evaluation resumes,
and evaluations of several stage-2 runs that share the folder simulate stage 1 once.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

from physgm.metrics.perceptual import perceptual_distance
from physgm.metrics.trajectory import score_videos
from physgm.model.checkpoint import load_model
from physgm.physics.materials import MATERIAL_NAMES
from physgm.train import rollout_env
from physgm.train.pairs import policy_fingerprint, settings_hash
from physgm.warp_runtime import preload

KEY_MATERIALS = ("metal", "jelly", "plasticine", "snow", "sand", "rubber")  # always reported
LABELS = {"pretrain": "stage 1", "dpo": "stage 2"}
METRICS = ("mean_distance", "mean_score", "mean_perceptual", "median_abs_log10_E_error", "material_accuracy")


def input_settings(hparams: dict, model) -> dict:
    """Views the model was trained on: stored by the DPO stage in the checkpoint's
    ``hyper_parameters``, else the encoder's native size."""
    inputs = dict(hparams.get("inputs") or {})
    inputs.setdefault("input_resolution", model.config.backbone.encoder.img_size)
    inputs.setdefault("num_views", 4)
    inputs.setdefault("background", 1.0)
    return inputs


class RolloutStore:
    """Each model's scored rollout of each scene, one ``.npz`` per (scene, model), written atomically.

    An evaluation that stops resumes where it stopped, and evaluations sharing the folder reuse each
    other's rollouts: stage 1 is simulated once for several stage-2 runs. A file is keyed by the
    model's weights (``policy_fingerprint``) and the evaluation's settings (``settings_hash`` of
    the data, views and simulation settings). The code is not in the key: after a change to the
    simulator or the scores, use a new folder.
    """

    def __init__(self, root: Path, settings: dict, models: dict) -> None:
        self.root = Path(root)
        self.settings = settings_hash(settings)
        self.fingerprints = {name: policy_fingerprint(m) for name, m in models.items()}

    def path(self, scene_id: str, name: str) -> Path:
        return self.root / f"{scene_id}-{self.fingerprints[name]}-{self.settings}.npz"

    def load(self, scene_id: str, name: str) -> tuple[dict, np.ndarray | None] | None:
        path = self.path(scene_id, name)
        if not path.is_file():
            return None
        with np.load(path, allow_pickle=False) as z:
            out = json.loads(str(z["out"]))
            frames = z["frames"] if "frames" in z.files else None
        return out, frames

    def save(self, scene_id: str, name: str, out: dict, frames: np.ndarray | None) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        path = self.path(scene_id, name)
        tmp = path.with_name(path.name + ".tmp.npz")
        arrays = {"out": np.array(json.dumps(out))}
        if frames is not None:
            arrays["frames"] = np.asarray(frames)
        np.savez(tmp, **arrays)
        os.replace(tmp, path)


def evaluate_scene(
    models: dict,
    scene,
    settings: rollout_env.SimSettings,
    workers: int,
    store: RolloutStore | None = None,
) -> tuple[dict, dict]:
    """Each model's mean-physics rollout of one scene: (row, {name: scored frames or None}).

    Rollouts found in ``store`` are read, not simulated again.
    """
    reference = rollout_env.reference_frames(scene, settings.n_frames)
    row = {**scene.truth(), "true_known": scene.true_known}

    def run(name: str) -> tuple[str, dict, np.ndarray | None]:
        gaussians, posterior = rollout_env.predict(models[name], scene.inputs)
        mean = posterior.mean()
        out = {
            "material": MATERIAL_NAMES[int(mean.material[0, 0])],
            "log10_E": float(mean.log10_E[0, 0]),
            "nu": float(mean.nu[0, 0]),
        }
        start, frames = time.perf_counter(), None
        try:
            physics = rollout_env.physics_spec(mean)
            result = rollout_env.evaluate_physics(
                scene, gaussians, physics, reference, settings, keep_frames=True
            )
            frames = result.frames
            out.update(score=result.distance, mode=result.mode, skipped=result.skipped, terms=result.terms)
        except (ValueError, RuntimeError) as err:
            out.update(score=None, error=f"{type(err).__name__}: {err}")
        out["seconds"] = round(time.perf_counter() - start, 2)
        out["abs_log10_E_error"] = abs(out["log10_E"] - scene.log10_E) if scene.true_known else None
        return name, out, frames

    stored = {n: store.load(scene.id, n) for n in models} if store else {}
    todo = [n for n in models if stored.get(n) is None]
    preload("cpu")  # no Warp module may load while the workers launch kernels
    with ThreadPoolExecutor(max(1, workers)) as pool:
        results = {name: (out, frames) for name, out, frames in pool.map(run, todo)}
    clips = {}
    for name in models:
        if name not in todo:
            row[name], clips[name] = stored[name]
            continue
        out, frames = results[name]
        clips[name] = frames
        # Scored here, in one thread: the tracker and the feature network are not shared across threads.
        out["distance"] = out["perceptual"] = None
        if frames is not None:
            d = score_videos(reference[: len(frames)], frames).distance
            out["distance"] = d if np.isfinite(d) else None
            out["perceptual"] = perceptual_distance(reference, frames)
        row[name] = out
        if store:
            store.save(scene.id, name, out, frames)
    return row, clips


def summarise(rows: list[dict], names: list[str]) -> dict:
    """Per-material and overall metrics of each model, and the stage-2 gains (1 - stage 2 / stage 1)."""
    present = sorted({r["material"] for r in rows}, key=MATERIAL_NAMES.index)
    groups = {
        m: [r for r in rows if r["material"] == m]
        for m in (*KEY_MATERIALS, *[p for p in present if p not in KEY_MATERIALS])
    }
    groups["overall"] = rows

    def values(subset: list[dict], name: str, key: str) -> list[float]:
        return [r[name][key] for r in subset if r[name].get(key) is not None]

    def stats(subset: list[dict], name: str) -> dict:
        err = values(subset, name, "abs_log10_E_error")
        acc = [r[name]["material"] == r["material"] for r in subset]
        return {
            "n": len(subset),
            "failed": len(subset) - len(values(subset, name, "distance")),
            "mean_distance": _mean(values(subset, name, "distance")),
            "mean_score": _mean(values(subset, name, "score")),
            "mean_perceptual": _mean(values(subset, name, "perceptual")),
            "median_abs_log10_E_error": float(np.median(err)) if err else None,
            "material_accuracy": float(np.mean(acc)) if acc else None,
        }

    out = {}
    for group, subset in groups.items():
        out[group] = {name: stats(subset, name) for name in names}
        if len(names) == 2:
            a, b = out[group][names[0]], out[group][names[1]]
            out[group]["gain"] = {
                k: (1.0 - b[k] / a[k]) if a[k] and b[k] is not None else None
                for k in ("mean_distance", "mean_perceptual", "median_abs_log10_E_error")
            }
    return out


def fmt(x: float | None, pct: bool = False) -> str:
    """A table cell or caption value: three decimals, or a signed percentage; a dash when missing."""
    return "—" if x is None else f"{100 * x:+.1f}%" if pct else f"{x:.3f}"


def markdown(summary: dict, names: list[str]) -> str:
    """The summary as one markdown table (one row per material, then overall)."""

    cols = [
        ("traj dist", "mean_distance"),
        ("perceptual", "mean_perceptual"),
        ("med abs dlog10E", "median_abs_log10_E_error"),
        ("mat acc", "material_accuracy"),
    ]
    head = ["material", "n"] + [f"{LABELS.get(n, n)} {c}" for c, _ in cols for n in names]
    head += ["dist gain", "perceptual gain", "E-err gain"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for group, s in summary.items():
        cells = [group, str(s[names[0]]["n"])] + [fmt(s[n][key]) for _, key in cols for n in names]
        gain = s.get("gain", {})
        cells += [
            fmt(gain.get(k), True) for k in ("mean_distance", "mean_perceptual", "median_abs_log10_E_error")
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_sheet(path: Path, scene, row: dict, reference: np.ndarray, clips: dict, fps: float) -> None:
    """One scene: its first input view, then reference / stage 1 / stage 2 keyframes, and the physics."""
    from physgm.pipeline.outputs import contact_sheet, keyframe_indices, save_png

    keys = keyframe_indices(len(reference), 6)
    rows = [("reference", reference, keys)]
    lines = [f"{scene.id}: true {row['material']} log10E={row['log10_E']:.2f} nu={row['nu']:.2f}"]
    for name, frames in clips.items():
        r = row[name]
        label = f"{LABELS.get(name, name)}: {r['material']} log10E={r['log10_E']:.2f}"
        lines += [label, f"  traj dist {fmt(r['distance'])}, perceptual {fmt(r['perceptual'])}"]
        if frames is not None:
            rows.append((label, frames, keyframe_indices(len(frames), 6)))
    preview = scene.inputs.images[0].permute(1, 2, 0).numpy()
    save_png(path, contact_sheet(preview, rows, lines, fps))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m physgm.train.evaluate_dpo", description=__doc__.split("\n")[0]
    )
    p.add_argument("--pretrain", required=True, help="stage-1 checkpoint")
    p.add_argument("--dpo", required=True, help="stage-2 (DPO) checkpoint")
    p.add_argument("--data", required=True, help="PhysAssets root with splits/ and reference videos")
    p.add_argument("--split", default="test", help="split(s) to evaluate, comma-separated (e.g. test,dpo)")
    p.add_argument("--video", default="drop", help="reference video name (videos/<name>.mp4)")
    p.add_argument("--max-scenes", type=int, default=None)
    p.add_argument(
        "--views", type=int, default=None, help="input views (default: as in DPO training, else 4)"
    )
    p.add_argument(
        "--input-resolution", type=int, default=None, help="input view size, px (default: as trained)"
    )
    p.add_argument("--resolution", type=int, default=None, help="render size, px (default: the reference's)")
    p.add_argument("--frames", type=int, default=None, help="frames compared (default: the whole reference)")
    p.add_argument(
        "--cells-across", type=int, default=None, help="MPM cells across the object (default: planner's)"
    )
    p.add_argument("--budget", type=float, default=None, help="seconds per rollout (default: none)")
    p.add_argument("--backend", default="warp")
    p.add_argument("--workers", type=int, default=2, help="models simulated at once (threads)")
    p.add_argument(
        "--seed", type=int, default=0, help="seed of the fixed evaluation views (as the datamodule)"
    )
    p.add_argument(
        "--out", type=Path, default=None, help="folder for JSON, table, sheets (default: by --dpo)"
    )
    p.add_argument(
        "--rollouts",
        type=Path,
        default=None,
        help="folder of each model's stored rollouts (default: OUT/rollouts); share it between "
        "evaluations to simulate a stage-1 model once",
    )
    a = p.parse_args(argv)

    torch.manual_seed(a.seed)
    pretrained, _ = load_model(a.pretrain)
    tuned, tuned_ckpt = load_model(a.dpo)
    models = {"pretrain": pretrained, "dpo": tuned}
    inputs = input_settings(tuned_ckpt.hparams, tuned)
    views = a.views or int(inputs["num_views"])
    res = a.input_resolution or inputs["input_resolution"]
    scenes = [
        s
        for split in a.split.split(",")
        for s in rollout_env.load_scenes(
            a.data, split.strip(), a.video, views, res, float(inputs["background"]), a.seed
        )
    ]
    scenes = scenes[: a.max_scenes]
    settings = rollout_env.SimSettings(
        resolution=a.resolution,
        n_frames=a.frames,
        backend=a.backend,
        planner={"cells_across": a.cells_across} if a.cells_across else {},
        device="cpu",
        budget={"max_seconds": a.budget},
    )
    out_dir = a.out or Path(a.dpo).resolve().parent / "evaluate_dpo"
    out_dir.mkdir(parents=True, exist_ok=True)
    store = RolloutStore(
        a.rollouts or out_dir / "rollouts",
        {
            "data": str(Path(a.data).resolve()),
            "video": a.video,
            "views": views,
            "input_resolution": res,
            "background": float(inputs["background"]),
            "seed": a.seed,
            "settings": dataclasses.asdict(settings),
        },
        models,
    )
    start, rows, sheets = time.perf_counter(), [], []
    for i, scene in enumerate(scenes):
        row, clips = evaluate_scene(models, scene, settings, a.workers, store)
        rows.append(row)
        if scene.material not in {m for m, _ in sheets}:
            sheet = out_dir / f"sheet_{scene.material}.png"
            write_sheet(
                sheet, scene, row, rollout_env.reference_frames(scene, settings.n_frames), clips, scene.fps
            )
            sheets.append((scene.material, str(sheet)))
        print(
            f"[{i + 1}/{len(scenes)}] {scene.id} ({scene.material}): "
            + ", ".join(f"{LABELS[n]} dist={row[n]['distance']}" for n in models),
            file=sys.stderr,
            flush=True,
        )
    names = list(models)
    summary = summarise(rows, names)
    table = markdown(summary, names)
    (out_dir / "evaluate_dpo.md").write_text(table)
    report = {
        "pretrain": a.pretrain,
        "dpo": a.dpo,
        "data": a.data,
        "split": a.split,
        "scenes": len(rows),
        "views": views,
        "input_resolution": res,
        "seconds": round(time.perf_counter() - start, 1),
        "settings": {
            "resolution": a.resolution,
            "frames": a.frames,
            "cells_across": a.cells_across,
            "budget": a.budget,
        },
        "summary": summary,
        "table": str(out_dir / "evaluate_dpo.md"),
        "sheets": dict(sheets),
        "per_scene": rows,
    }
    (out_dir / "evaluate_dpo.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report))
    print(table, file=sys.stderr)
    return 0


def _mean(x: list[float]) -> float | None:
    return float(np.mean(x)) if x else None


if __name__ == "__main__":
    sys.exit(main())
