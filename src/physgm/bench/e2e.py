"""``python -m physgm.bench e2e``: the whole photo -> clip pipeline on the shipped examples, as JSON.

Runs ``simulate.py``'s pipeline (same config: conf/simulate.yaml) on every example under
examples/ for each scene and prints ``{"runs": [{"input", "scene", "material", "mode", "frames",
"res", "seconds": {"load", "model", "plan", "simulate", "render", "write", "total"}, ...}],
"machine": {...}}``. Until a trained checkpoint ships, ``--random-ckpt`` times the pipeline
with a randomly initialised tiny model (same compute, meaningless physics: the material is
whatever the untrained head's argmax is, so pass ``--material`` to time a chosen one).
Wall-clock numbers depend on the machine's load, which is reported (``loadavg``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
EXAMPLES = ROOT / "examples"
SCENES = ("drop", "stretch", "push")


def example_inputs(folder: Path) -> list[Path]:
    """Photos (png/jpg) and posed-view folders (with cameras.json) under ``folder``."""
    photos = [p for p in folder.iterdir() if p.suffix.lower() in {".png", ".jpg", ".jpeg"}]
    views = [p for p in folder.iterdir() if p.is_dir() and (p / "cameras.json").is_file()]
    return sorted(photos + views)


def machine() -> dict:
    """What a run's wall-clock numbers depend on: cores, load, Python."""
    return {
        "cpus": os.cpu_count(),
        "loadavg": [round(x, 2) for x in os.getloadavg()],
        "python": platform.python_version(),
    }


def compose_run(overrides: list[str]):
    from hydra import compose, initialize_config_dir

    from physgm.pipeline import from_hydra

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return from_hydra(compose("simulate", overrides=overrides))


def random_checkpoint(folder: Path) -> Path:
    """A randomly initialised default (tiny CPU) PhysGM in the LitPretrain checkpoint layout."""
    import torch

    from physgm.model import PhysGM, PhysGMConfig
    from physgm.model.checkpoint import save_checkpoint

    torch.manual_seed(0)
    path = folder / "random_tiny.ckpt"
    save_checkpoint(PhysGM(PhysGMConfig(), load_pretrained=False), path)
    return path


def bench_one(path: Path, scene: str, ckpt: Path, out: Path, args) -> dict:
    from physgm.pipeline import UserError, run_pipeline

    overrides = [
        f"input={path}",
        f"ckpt={ckpt}",
        f"scene={scene}",
        f"paths.output_dir={out}",
        f"output.resolution={args.res}",
        f"output.frames={args.frames}",
        "output.progress=false",
        f"device={args.device}",
    ]
    if args.material:
        overrides.append(f"physics.material={args.material}")
    row = {"input": path.name, "scene": scene, "frames": args.frames, "res": args.res}
    start = time.perf_counter()
    try:
        report = run_pipeline(compose_run(overrides)).report
    except UserError as err:
        return {**row, "error": str(err)}
    mean = report["runs"][0]
    return {
        **row,
        "material": mean["material"],
        "mode": mean["mode"],
        "predicted_error_px": round(mean["predicted_error_px"], 4),
        "E_used": mean["E_used"],
        "particles": mean["particles"],
        "gaussians": report["object"]["gaussians"],
        "substeps": mean["substeps"],
        "rest_frame": mean["rest_frame"],
        "seconds": report["seconds"],
        "wall_s": round(time.perf_counter() - start, 3),
        "loadavg_1min": round(os.getloadavg()[0], 2),
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m physgm.bench e2e", description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", type=Path, default=ROOT / "checkpoints" / "physgm_tiny.ckpt")
    parser.add_argument(
        "--random-ckpt", action="store_true", help="time with a randomly initialised tiny model"
    )
    parser.add_argument(
        "--inputs", default="", help="comma-separated example names (default: all under examples/)"
    )
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument(
        "--material", default="", help="override the material (physics.material) for every run"
    )
    parser.add_argument("--frames", type=int, default=50)
    parser.add_argument("--res", type=int, default=256)
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--out", type=Path, default=None, help="keep the run folders here (default: a temp dir)"
    )
    args = parser.parse_args(argv)

    inputs = example_inputs(EXAMPLES)
    if args.inputs:
        wanted = set(args.inputs.split(","))
        inputs = [p for p in inputs if p.name in wanted or p.stem in wanted]
    scenes = [s for s in args.scenes.split(",") if s]
    with tempfile.TemporaryDirectory(prefix="physgm-e2e-") as tmp:
        ckpt = random_checkpoint(Path(tmp)) if args.random_ckpt else args.ckpt
        if not args.random_ckpt and not ckpt.is_file():
            from physgm.model.checkpoint import missing_checkpoint_message

            sys.exit(f"error: {missing_checkpoint_message(ckpt)}; or time with --random-ckpt")
        out_root = args.out or Path(tmp) / "runs"
        runs = []
        for path in inputs:
            for scene in scenes:
                out = out_root / f"{path.stem}_{scene}"
                runs.append(bench_one(path, scene, ckpt, out, args))
                print(json.dumps(runs[-1]), file=sys.stderr)  # progress while the suite runs
    result = {
        "runs": runs,
        "ckpt": "random-init tiny model (timing only)" if args.random_ckpt else str(ckpt),
        "machine": machine(),
    }
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
