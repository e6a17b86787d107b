"""``python -m physgm.bench render``: warp vs torch renderer speed and agreement, as JSON.

Scene: an object of radius 0.5 m (Gaussian centres uniform in the ball) seen from 1.8 m by a
40 degree camera, scales 1-3 % of the 1 m object size (log-uniform per axis), random
orientations, opacities and colours. Each case is warmed up once (Warp compiles / caches its
kernels), then timed as the median of a few repeats: `fwd_ms` is an inference forward
(no autograd graph), `fwd_bwd_ms` a forward with autograd plus the backward of a random
linear loss on rgb and alpha; `threads` is torch's intra-op thread count for the torch
reference and the raster thread count for warp. The two backends are timed in alternation so
both see the same machine load; wall-clock numbers still depend on it (see "machine").
"""

from __future__ import annotations

import argparse
import contextlib
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
    eye = 1.8 * torch.tensor(
        [
            math.cos(azimuth) * math.cos(elevation),
            math.sin(azimuth) * math.cos(elevation),
            math.sin(elevation),
        ]
    )
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


def _forward(scene: dict, backend: str, grad: bool, **options):
    from physgm.render import rasterize  # late import, see main()

    params = {
        k: v.clone().requires_grad_(grad)
        for k, v in scene.items()
        if k in ("means", "quats", "scales", "opacities", "colors")
    }
    rgb, alpha, _ = rasterize(
        **params,
        viewmats=scene["viewmats"],
        Ks=scene["Ks"],
        width=scene["width"],
        height=scene["height"],
        backend=backend,
        **options,
    )
    return rgb, alpha


@contextlib.contextmanager
def _torch_threads(num: int | None):
    previous = torch.get_num_threads()
    torch.set_num_threads(num or previous)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


class _Timer:
    """Runs one backend on one scene and records wall-clock times (ms) of each call."""

    def __init__(self, scene: dict, backend: str, threads: int):
        self.scene, self.backend, self.threads = scene, backend, threads
        gen = torch.Generator().manual_seed(1)
        self.w_rgb = torch.randn(1, scene["height"], scene["width"], 3, generator=gen)
        self.w_alpha = torch.randn(1, scene["height"], scene["width"], 1, generator=gen)
        # torch: intra-op threads; warp: raster threads (its torch glue runs on one thread)
        self.torch_threads = threads if backend == "torch" else None
        self.options = {"num_threads": threads} if backend == "warp" else {}
        self.times = {"fwd": [], "fwd_bwd": []}

    def image(self) -> torch.Tensor:
        with torch.no_grad(), _torch_threads(self.torch_threads):
            rgb, alpha = _forward(self.scene, self.backend, grad=False, **self.options)
        return torch.cat([rgb, alpha], dim=-1)

    def fwd_bwd(self) -> float:
        with _torch_threads(self.torch_threads):
            start = time.perf_counter()
            rgb, alpha = _forward(self.scene, self.backend, grad=True, **self.options)
            ((rgb * self.w_rgb).sum() + (alpha * self.w_alpha).sum()).backward()
            elapsed = 1e3 * (time.perf_counter() - start)
        self.times["fwd_bwd"].append(elapsed)
        return elapsed

    def fwd(self) -> float:
        with torch.no_grad(), _torch_threads(self.torch_threads):
            start = time.perf_counter()
            _forward(self.scene, self.backend, grad=False, **self.options)
            elapsed = 1e3 * (time.perf_counter() - start)
        self.times["fwd"].append(elapsed)
        return elapsed

    def case(self) -> dict:
        return {
            "backend": self.backend,
            "n": self.scene["means"].shape[0],
            "res": self.scene["width"],
            "fwd_ms": round(statistics.median(self.times["fwd"]), 2),
            "fwd_bwd_ms": round(statistics.median(self.times["fwd_bwd"]), 2),
            "threads": self.threads,
        }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m physgm.bench render")
    parser.add_argument("--repeats", type=int, default=11, help="timed runs per case (median)")
    parser.add_argument("--threads", type=int, default=2, help="raster threads of the warp backend")
    args = parser.parse_args(argv)
    # Warp prints a banner when physgm.render is first imported, which would break the
    # one-JSON-object output, so it is silenced before that (late) import in _forward.
    wp.config.log_level = wp.LOG_WARNING
    load_before = os.getloadavg()
    cases, speedup = [], {}
    for num, res in SIZES:
        scene = make_scene(num, res)
        # The torch reference runs with 1 or with all intra-op threads, whichever is faster in
        # a warm-up: on a shared 2-core machine two OpenMP threads can be many times slower.
        probes = [_Timer(scene, "torch", t) for t in sorted({1, torch.get_num_threads()})]
        ref = min(probes, key=lambda timer: timer.fwd_bwd())
        ref.times["fwd_bwd"].clear()
        warp = _Timer(scene, "warp", args.threads)
        warp.fwd_bwd()  # warm-up: Warp kernel load, allocator, thread pool
        warp.times["fwd_bwd"].clear()
        for _ in range(args.repeats):  # interleaved, so both see the same machine load
            for timer in (ref, warp):
                timer.fwd()
                timer.fwd_bwd()
        ref_case, warp_case = ref.case(), warp.case()
        ref_case["max_abs_diff_vs_torch"] = 0.0
        warp_case["max_abs_diff_vs_torch"] = float((warp.image() - ref.image()).abs().max())
        cases += [ref_case, warp_case]
        speedup[f"{num}x{res}"] = round(ref_case["fwd_bwd_ms"] / warp_case["fwd_bwd_ms"], 1)
    report = {
        "cases": cases,
        "speedup_vs_torch": speedup,
        "machine": {
            "cpus": os.cpu_count(),
            "loadavg_1min_before": round(load_before[0], 2),
            "loadavg_1min_after": round(os.getloadavg()[0], 2),
            # torch's idle OpenMP threads spin this long before sleeping; `import physgm` sets it
            "gomp_spincount": os.environ.get("GOMP_SPINCOUNT"),
        },
    }
    print(json.dumps(report))
    return report


if __name__ == "__main__":
    main()
