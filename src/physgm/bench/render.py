"""``python -m physgm.bench render``: warp vs torch renderer speed and agreement, as JSON.

Scene: an object of radius 0.5 m (Gaussian centres uniform in the ball) seen from 1.8 m by a
40 degree camera, scales 1-3 % of the 1 m object size (log-uniform per axis), random
orientations, opacities and colours. Each case is warmed up once (Warp compiles / caches its
kernels), then timed as the median of a few repeats: `fwd_ms` is an inference forward
(no autograd graph), `fwd_bwd_ms` a forward with autograd plus the backward of a random
linear loss on rgb and alpha. Wall-clock numbers depend on machine load, reported under
"machine".
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time

import torch
import warp as wp

SIZES = ((4096, 64), (16384, 128))  # (number of Gaussians, image side in px)


def make_scene(num: int, res: int, seed: int = 0) -> dict:
    """Random object-like scene and one camera at 1.8 m looking at the origin (float32, CPU)."""
    gen = torch.Generator().manual_seed(seed)
    direction = torch.nn.functional.normalize(torch.randn(num, 3, generator=gen), dim=-1)
    radius = 0.5 * torch.rand(num, 1, generator=gen) ** (1.0 / 3.0)  # uniform in the ball
    log_s = torch.empty(num, 3).uniform_(math.log(0.01), math.log(0.03), generator=gen)
    azimuth, elevation = 0.3, 0.2
    eye = 1.8 * torch.tensor([math.cos(azimuth) * math.cos(elevation),
                              math.sin(azimuth) * math.cos(elevation), math.sin(elevation)])
    forward = -eye / eye.norm()  # OpenCV camera: x right, y down, z forward; world +z up
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, torch.tensor([0.0, 0.0, 1.0])), dim=0)
    down = torch.linalg.cross(forward, right)
    rot = torch.stack([right, down, forward])
    viewmat = torch.eye(4)
    viewmat[:3, :3] = rot
    viewmat[:3, 3] = -rot @ eye
    focal = 0.5 * res / math.tan(math.radians(20.0))
    K = torch.tensor([[focal, 0.0, res / 2], [0.0, focal, res / 2], [0.0, 0.0, 1.0]])
    return {
        "means": direction * radius,
        "quats": torch.randn(num, 4, generator=gen),
        "scales": log_s.exp(),
        "opacities": torch.rand(num, generator=gen),
        "colors": torch.rand(num, 3, generator=gen),
        "viewmats": viewmat[None],
        "Ks": K[None],
        "width": res,
        "height": res,
    }


def _forward(scene: dict, backend: str, grad: bool):
    from physgm.render import rasterize  # late import, see main()

    params = {k: v.clone().requires_grad_(grad) for k, v in scene.items()
              if k in ("means", "quats", "scales", "opacities", "colors")}  # fmt: skip
    rgb, alpha, _ = rasterize(**params, viewmats=scene["viewmats"], Ks=scene["Ks"],
                              width=scene["width"], height=scene["height"], backend=backend)  # fmt: skip
    return rgb, alpha


def _time_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - start))
    return statistics.median(times)


def run_case(scene: dict, backend: str, repeats: int) -> tuple[dict, torch.Tensor]:
    weights = torch.Generator().manual_seed(1)
    w_rgb = torch.randn(1, scene["height"], scene["width"], 3, generator=weights)
    w_alpha = torch.randn(1, scene["height"], scene["width"], 1, generator=weights)

    def fwd():
        with torch.no_grad():
            return _forward(scene, backend, grad=False)

    def fwd_bwd():
        rgb, alpha = _forward(scene, backend, grad=True)
        ((rgb * w_rgb).sum() + (alpha * w_alpha).sum()).backward()

    fwd_bwd()  # warm-up: Warp kernel load, allocator, thread pool
    rgb, alpha = fwd()
    case = {
        "backend": backend,
        "n": scene["means"].shape[0],
        "res": scene["width"],
        "fwd_ms": round(_time_ms(fwd, repeats), 2),
        "fwd_bwd_ms": round(_time_ms(fwd_bwd, repeats), 2),
    }
    return case, torch.cat([rgb, alpha], dim=-1)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m physgm.bench render")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per warp case")
    parser.add_argument("--torch-repeats", type=int, default=3, help="timed runs per torch case")
    args = parser.parse_args(argv)
    # Warp prints a banner when physgm.render is first imported, which would break the
    # one-JSON-object output, so it is silenced before that (late) import in _forward.
    wp.config.quiet = True
    load_before = os.getloadavg()
    cases, speedup = [], {}
    for num, res in SIZES:
        scene = make_scene(num, res)
        ref_case, ref_img = run_case(scene, "torch", args.torch_repeats)
        warp_case, warp_img = run_case(scene, "warp", args.repeats)
        ref_case["max_abs_diff_vs_torch"] = 0.0
        warp_case["max_abs_diff_vs_torch"] = float((warp_img - ref_img).abs().max())
        cases += [ref_case, warp_case]
        speedup[f"{num}x{res}"] = round(ref_case["fwd_bwd_ms"] / warp_case["fwd_bwd_ms"], 1)
    report = {
        "cases": cases,
        "speedup_vs_torch": speedup,
        "machine": {
            "cpus": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "loadavg_1min_before": round(load_before[0], 2),
            "loadavg_1min_after": round(os.getloadavg()[0], 2),
        },
    }
    print(json.dumps(report))
    return report


if __name__ == "__main__":
    main()
