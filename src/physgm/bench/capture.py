"""``python -m physgm.bench capture``: ``simulate.py`` on a capture-sized ``.ply``, as JSON.

A capture from another 3DGS tool holds hundreds of thousands to millions of Gaussians, where the
model's own reconstructions hold tens of thousands. This bench writes a stand-in (``capture_blob``:
N Gaussians filling an ellipsoid of 8 x 6 x 7 cm, random orientations, opacities and colours,
scales about 4 mm), runs ``simulate.py`` on it with a chosen material in a child process per size,
and prints ``{"runs": [{"gaussians", "material", "mode", "particles", "substeps", "seconds":
{stages}, "peak_rss_gb", "npz_mb"}], "machine": {...}}``. Peak memory is the child's own
(``ru_maxrss``), so sizes do not mix. Wall-clock numbers depend on the machine's load.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

from physgm.bench.e2e import compose_run, machine
from physgm.gaussians import Gaussians, write_ply
from physgm.physics.materials import MATERIAL_NAMES


def capture_blob(n: int, seed: int = 0) -> Gaussians:
    """n Gaussians filling an ellipsoid of 8 x 6 x 7 cm (semi-axes) centred 30 cm up, like a dense
    3DGS capture of a small object: random orientations, scales 4 mm x exp(0.3 z), opacities
    0.2-1, random colours."""
    g = torch.Generator().manual_seed(seed)
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    radius = torch.rand(n, 1, generator=g) ** (1 / 3)  # uniform in the volume
    means = direction * radius * torch.tensor([0.08, 0.06, 0.07]) + torch.tensor([0.0, 0.0, 0.3])
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    scales = torch.exp(torch.randn(n, 3, generator=g) * 0.3) * 0.004
    opacities = torch.rand(n, generator=g) * 0.8 + 0.2
    return Gaussians(means, quats, scales, opacities, torch.rand(n, 3, generator=g))


def run_child(ply: Path, out: Path, material: str, frames: int, res: int) -> dict:
    """The pipeline on ``ply`` in this process (the child's side); its report and peak memory."""
    from physgm.pipeline import run_pipeline

    overrides = [
        f"input={ply}",
        f"physics.material={material}",
        f"paths.output_dir={out}",
        f"output.frames={frames}",
        f"output.resolution={res}",
        "output.progress=false",
    ]
    report = run_pipeline(compose_run(overrides)).report
    mean = report["runs"][0]
    npz = out / "gaussians_t.npz"
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    return {
        "gaussians": report["object"]["gaussians"],
        "material": mean["material"],
        "mode": mean["mode"],
        "particles": mean["particles"],
        "substeps": mean["substeps"],
        "seconds": report["seconds"],
        "peak_rss_gb": round(peak_kib * 1024 / 1e9, 3),
        "npz_mb": round(npz.stat().st_size / 1e6, 1) if npz.is_file() else None,
    }


def bench_size(n: int, folder: Path, args) -> dict:
    """Writes the blob of n Gaussians into ``folder`` and runs the pipeline on it in a child process."""
    ply = folder / f"blob_{n}.ply"
    write_ply(capture_blob(n), ply)
    out = folder / f"run_{n}"
    cmd = [sys.executable, "-m", "physgm.bench.capture", "--child", str(ply), "--out", str(out)]
    cmd += ["--material", args.material, "--frames", str(args.frames), "--res", str(args.res)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        last = done.stderr.strip().splitlines()[-1:] or [f"exit status {done.returncode}"]
        return {"gaussians": n, "error": last[0]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(
        prog="python -m physgm.bench capture", description=__doc__.splitlines()[0]
    )
    parser.add_argument(
        "--gaussians", type=int, nargs="+", default=[400_000], help="blob sizes, one run each"
    )
    parser.add_argument("--material", default="jelly")
    parser.add_argument("--frames", type=int, default=50)
    parser.add_argument("--res", type=int, default=256)
    parser.add_argument(
        "--out", type=Path, default=None, help="keep the blobs and runs here (default: a temp dir)"
    )
    # internal: one run in this process, the PLY given (what bench_size starts)
    parser.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child is not None:
        row = run_child(args.child, args.out, args.material, args.frames, args.res)
        print(json.dumps(row))
        return row
    if any(n < 1 for n in args.gaussians):
        parser.error(f"--gaussians must be positive, got {args.gaussians}")
    if args.material not in MATERIAL_NAMES:
        parser.error(f"--material {args.material!r} is unknown; choose one of: {', '.join(MATERIAL_NAMES)}")
    with tempfile.TemporaryDirectory(prefix="physgm-capture-") as tmp:
        folder = args.out or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        runs = []
        for n in args.gaussians:
            runs.append(bench_size(n, folder, args))
            print(json.dumps(runs[-1]), file=sys.stderr)  # progress while the suite runs
    result = {"runs": runs, "machine": machine()}
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
