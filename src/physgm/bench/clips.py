"""``python -m physgm.bench clips REF RUN [RUN ...]``: how far simulated clips are from a reference clip.

Each argument is a run folder written by ``simulate.py`` (its ``gaussians_t.npz`` and
``report.json``). Every RUN must come from the same input as REF (the same Gaussians), simulated
with other settings: a planner option, a grid resolution, a CFL number, another ground contact.
The distance is the one ``bench sim --only options`` reports: each Gaussian's centre projected
into REF's camera at REF's output resolution, in pixels, compared frame by frame (a clip that came
to rest early repeats its last stored frame). Per RUN the JSON gives the mean over frames and
Gaussians, the worst frame's mean and the largest single distance, next to what the run cost
(simulated seconds, sub-steps, the frame it came to rest at) and how much it still moved at the
end (the largest per-frame motion of a Gaussian over the last ``--tail`` frames, pixels), which
is what decides whether the simulator's rest stop can fire.

    python simulate.py input=examples/jelly_cube.png paths.output_dir=outputs/a
    python simulate.py input=examples/jelly_cube.png solver.cfl=0.6 paths.output_dir=outputs/b
    python -m physgm.bench clips outputs/a outputs/b
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
from pathlib import Path

import numpy as np
import torch

from physgm.bench.drop_scene import project
from physgm.cameras import Cameras, intrinsics_from_fov
from physgm.view.sequence import SEQUENCE_FILE, GaussianSequence


def _camera(camera: GaussianSequence, resolution: int) -> Cameras:
    """``camera``'s clip camera at a square ``resolution``."""
    fov_deg = math.degrees(camera.camera_fov_y)  # square image: the horizontal field of view too
    return Cameras(
        c2w=torch.as_tensor(camera.camera_c2w, dtype=torch.float64)[None],
        Ks=intrinsics_from_fov(fov_deg, resolution, resolution).double()[None],
        width=resolution,
        height=resolution,
    )


def pixel_coordinates(seq: GaussianSequence, cameras: Cameras, t: int) -> np.ndarray:
    """Centres of frame t of ``seq`` [N, 2] in pixels of ``cameras`` (a clip that came to rest
    repeats its last stored frame)."""
    return project(cameras, torch.as_tensor(seq.frame(t)[0], dtype=torch.float64)).numpy()


def compare(reference: GaussianSequence, run: GaussianSequence, resolution: int) -> dict[str, float]:
    """Projected centre distance of ``run`` to ``reference``, px: mean, worst frame's mean, largest."""
    if len(run.colors) != len(reference.colors):
        raise ValueError(
            f"the clips hold {len(reference.colors)} and {len(run.colors)} Gaussians: compare runs "
            "of the same input (the same photo and checkpoint, or the same .ply)"
        )
    if run.n_frames != reference.n_frames or run.fps != reference.fps:
        raise ValueError(
            f"the clips have {reference.n_frames} frames at {reference.fps} fps and {run.n_frames} at "
            f"{run.fps} fps: compare runs with the same output.frames and output.fps"
        )
    cameras = _camera(reference, resolution)
    per_frame, largest = [], 0.0
    for t in range(reference.n_frames):
        dist = np.linalg.norm(
            pixel_coordinates(run, cameras, t) - pixel_coordinates(reference, cameras, t), axis=-1
        )  # [N]
        per_frame.append(float(dist.mean()))
        largest = max(largest, float(dist.max()))
    return {
        "error_px": float(np.mean(per_frame)),
        "error_px_worst_frame": max(per_frame),
        "error_px_largest": largest,
    }


def tail_motion(seq: GaussianSequence, resolution: int, tail: int) -> float:
    """Largest motion of a Gaussian between consecutive frames over the last ``tail`` frames, px
    (0 when the clip came to rest that early: its last frames repeat)."""
    cameras = _camera(seq, resolution)
    first = max(seq.n_frames - tail - 1, 0)
    px = [pixel_coordinates(seq, cameras, t) for t in range(first, seq.n_frames)]
    steps = [float(np.linalg.norm(b - a, axis=-1).max()) for a, b in itertools.pairwise(px)]
    return max(steps, default=0.0)


def _load(folder: Path) -> tuple[GaussianSequence, dict]:
    path = folder / SEQUENCE_FILE
    if not path.is_file():
        raise ValueError(f"{folder} has no {SEQUENCE_FILE}: give run folders written by simulate.py")
    report_path = folder / "report.json"
    report = json.loads(report_path.read_text()) if report_path.is_file() else {}
    return GaussianSequence.load(path), report


def _cost(report: dict) -> dict:
    run = (report.get("runs") or [{}])[0]
    return {
        "seconds_simulate": report.get("seconds", {}).get("simulate"),
        "substeps": run.get("substeps"),
        "particles": run.get("particles"),
        "rest_frame": run.get("rest_frame"),
        "mode": run.get("mode"),
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m physgm.bench clips", description=__doc__.split("\n")[0])
    parser.add_argument("reference", type=Path, help="run folder of the reference clip")
    parser.add_argument("runs", type=Path, nargs="+", help="run folders to compare with it")
    parser.add_argument("--tail", type=int, default=5, help="frames at the end whose motion is reported")
    args = parser.parse_args(argv)
    if args.tail < 1:
        parser.error(f"--tail must be >= 1, got {args.tail}")
    try:
        reference, ref_report = _load(args.reference)
        resolution = int(ref_report.get("output", {}).get("resolution", 256))
        tail = tail_motion(reference, resolution, args.tail)
        rows = [{"run": str(args.reference), **_cost(ref_report), "tail_motion_px": tail}]
        for folder in args.runs:
            seq, report = _load(folder)
            rows.append(
                {
                    "run": str(folder),
                    **compare(reference, seq, resolution),
                    **_cost(report),
                    "tail_motion_px": tail_motion(seq, resolution, args.tail),
                }
            )
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    out = {"reference": str(args.reference), "resolution": resolution, "clips": rows}
    print(json.dumps(out, indent=1))
    return out
