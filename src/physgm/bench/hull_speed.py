"""Visual-hull search benchmark: the Warp kernel against its torch twin; prints one JSON object.

    python -m physgm.bench hull --data data/synthetic_photo_g24 [--split val] [--assets 32]
                                [--resolution 128] [--repeats 3] [--threads 2]

Each batch is what the model's Gaussian head gets during evaluation with 4 input views (4 assets,
their masks and cameras at ``--resolution``), run through ``hull_depth_range`` and
``_hull_depth_range_torch`` in turn, so both see the same load; one untimed call first loads the
kernel. The report gives each one's median and range over all batches and repeats, and the largest
share of rays on which the two differ (by more than 1e-5). Wall-clock numbers are noisy when other
processes share the CPU.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Any

import torch

from physgm.cameras import Cameras, pixel_rays
from physgm.data.datamodule import PhysAssetsDataModule
from physgm.errors import UserError
from physgm.model.config import GaussianHeadConfig
from physgm.model.hull import _hull_depth_range_torch, hull_depth_range


def hull_inputs(root: Path, split: str, assets: int, resolution: int) -> list[tuple]:
    """(masks [B, V, 1, H, W], c2w [B, V, 4, 4], Ks [B, V, 3, 3], directions [B, V, H, W, 3]) per
    batch of up to 4 of the split's first ``assets`` assets, 4 input views each."""
    data = PhysAssetsDataModule(
        str(root), batch_size=4, eval_p_single=0.0, num_targets=4, input_resolution=resolution,
        target_resolution=resolution, test_split=split,
    )  # fmt: skip
    data.setup("test")
    batches = []
    for batch in data.test_dataloader():
        b, v, _, height, width = batch.images.shape
        cams = Cameras(batch.c2w.reshape(-1, 4, 4).float(), batch.Ks.reshape(-1, 3, 3).float(), width, height)
        _, directions = pixel_rays(cams)
        batches.append(
            (batch.masks.float(), cams.c2w.reshape(b, v, 4, 4), cams.Ks.reshape(b, v, 3, 3),
             directions.reshape(b, v, height, width, 3))
        )  # fmt: skip
        if 4 * len(batches) >= assets:
            break
    return batches


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m physgm.bench hull", description=__doc__.split("\n")[0])
    parser.add_argument(
        "--data", type=Path, required=True, help="a PhysAssets root (e.g. data/synthetic_photo_g24)"
    )
    parser.add_argument("--split", default="val")
    parser.add_argument("--assets", type=int, default=32)
    parser.add_argument("--resolution", type=int, default=128, help="input views, px")
    parser.add_argument("--repeats", type=int, default=3, help="passes over the batches")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: leave torch's default)")
    args = parser.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    if not args.data.is_dir():
        raise UserError(
            f"--data {args.data} is not a folder; make a data set with python -m physgm.data.synth"
        )
    head = GaussianHeadConfig()
    batches = hull_inputs(args.data, args.split, args.assets, args.resolution)
    if not batches:
        raise UserError(f"--data {args.data} has no assets in split {args.split!r}")
    seconds: dict[str, list[float]] = {"warp": [], "torch": []}
    differing = 0.0
    with torch.no_grad():
        hull_depth_range(*batches[0], head.near, head.far)  # warm-up: the kernel's module loads
        for _ in range(max(1, args.repeats)):
            for inputs in batches:
                ranges = {}
                for name, search in (("warp", hull_depth_range), ("torch", _hull_depth_range_torch)):
                    start = time.perf_counter()
                    ranges[name] = search(
                        *inputs, head.near, head.far, head.hull_samples, head.mask_threshold
                    )
                    seconds[name].append(time.perf_counter() - start)
                for got, ref in zip(ranges["warp"], ranges["torch"], strict=True):
                    differing = max(differing, ((got - ref).abs() > 1e-5).float().mean().item())
    report = {
        "suite": "hull",
        "torch_threads": torch.get_num_threads(),
        "data": str(args.data),
        "batches": len(batches),
        "views": 4,
        "resolution": args.resolution,
        "mask_cover": statistics.mean(float((m > head.mask_threshold).float().mean()) for m, *_ in batches),
        **{f"{name}_ms_median": 1000 * statistics.median(s) for name, s in seconds.items()},
        **{f"{name}_ms_range": [1000 * min(s), 1000 * max(s)] for name, s in seconds.items()},
        "speedup_median": statistics.median(seconds["torch"]) / statistics.median(seconds["warp"]),
        "rays_differing_max_share": differing,
    }
    print(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
