"""Synthetic PhysAssets: ``python -m physgm.data.synth --out DIR --count N --seed S``.

Each asset is a procedural shape (shapes.py) dressed as one material (appearance.py), turned
into 3D Gaussians (procedural.py), rendered from 32 views with ``physgm.render.rasterize``,
labelled with its true physics and an imitation annotator's labels (annotation.py), and,
for a subset, given a reference drop video simulated with the true physics (video.py).

Everything an asset contains derives from ``(seed, index)``, so the same command gives the
same bytes whatever the number of workers, and an interrupted run resumes where it stopped.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing as mp
import os
import sys
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from physgm.cameras import Cameras, orbit_cameras
from physgm.data.annotation import AnnotatorConfig, annotate
from physgm.data.format import CAMERA_RADIUS, FOV_DEG, SPLITS, SPLITS_DIR, view_grid
from physgm.data.priors import constitutive_model, material_names, sample_physics
from physgm.data.procedural import make_object
from physgm.data.shapes import FAMILIES
from physgm.data.writer import TMP_PREFIX, atomic_asset_dir, to_rgba8, write_json, write_views_cameras_physics
from physgm.gaussians import Gaussians, write_ply

GENERATOR_VERSION = 3  # 2: photo textures and varied light (off by default: version-1 bytes otherwise);
# 3: a photographed texture carries the stiffness and poisson cues (appearance.cued_photo)
_RENDER_THREADS = 2  # CPU threads per rasterize call; 1 inside worker processes (see _worker_init)
CONFIG_FILE = "synth.json"  # at the data set root: the settings every asset was made with
# Settings added after data sets were made: a synth.json without one was made at this value.
_ADDED_SINCE = {"gaussians_file": True}


@dataclass
class SynthConfig:
    """Settings of one synthetic data set (everything that changes the bytes of an asset)."""

    count: int = 100  # number of assets
    seed: int = 0
    resolution: int = 128  # square views, pixels
    gaussians: int = 8000  # Gaussians per object
    video_fraction: float = 0.2  # share of assets with a reference drop video
    backend: str = "warp"  # physgm.render backend used for the views and videos
    materials: list[str] | None = None  # restrict to these materials (default: all)
    families: list[str] | None = None  # restrict to these shape families (default: all)
    photo_textures: float = (
        0.0  # chance an asset wears a photographed material texture (physgm.data.photo_textures)
    )
    varied_light: bool = False  # a random light per asset instead of the fixed one
    gaussians_file: bool = True  # write gaussians.ply (at 24,000 Gaussians two thirds of an asset's bytes)
    annotator: AnnotatorConfig = field(default_factory=AnnotatorConfig)
    # Split shares: assets without video -> train / val / test; with video -> dpo / test.
    val_fraction: float = 0.05
    test_fraction: float = 0.05
    video_test_fraction: float = 0.3

    def __post_init__(self) -> None:
        if isinstance(self.annotator, dict):
            self.annotator = AnnotatorConfig.from_dict(self.annotator)
        names, fams = material_names(), list(FAMILIES)
        bad = [m for m in (self.materials or []) if m not in names]
        if bad:
            raise ValueError(f"unknown materials {bad}; choose from {', '.join(names)}")
        bad = [f for f in (self.families or []) if f not in fams]
        if bad:
            raise ValueError(f"unknown shape families {bad}; choose from {', '.join(fams)}")
        if self.count < 0 or self.resolution < 8 or not 0 <= self.video_fraction <= 1:
            raise ValueError(
                f"need count >= 0, resolution >= 8, video_fraction in [0, 1]; got {self.count}, "
                f"{self.resolution}, {self.video_fraction}"
            )

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["annotator"]["lookalikes"] = [list(p) for p in self.annotator.lookalikes]
        d["generator_version"] = GENERATOR_VERSION
        return d


def asset_id(index: int) -> str:
    return f"syn_{index:06d}"


@dataclass(frozen=True)
class AssetPlan:
    """What can be known about an asset without generating it."""

    index: int
    split: str
    video: bool
    material: str
    family: str


def plan_asset(cfg: SynthConfig, index: int) -> AssetPlan:
    """Split, video flag, material and family of asset ``index`` (cheap, deterministic)."""
    rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, index, 0]))
    u_video, u_split, u_mat, u_fam = rng.random(4)
    video = bool(u_video < cfg.video_fraction)
    if video:
        split = "test" if u_split < cfg.video_test_fraction else "dpo"
    else:
        split = (
            "val"
            if u_split < cfg.val_fraction
            else "test"
            if u_split < cfg.val_fraction + cfg.test_fraction
            else "train"
        )
    mats = cfg.materials or list(material_names())
    fams = cfg.families or list(FAMILIES)
    return AssetPlan(index, split, video, mats[int(u_mat * len(mats))], fams[int(u_fam * len(fams))])


def view_cameras(resolution: int) -> tuple[Cameras, list[float], list[float]]:
    """The 32 synthetic views (4 elevations x 8 azimuths, radius 1.8 m, FOV 34 degrees)."""
    az, el = view_grid()
    return orbit_cameras(az, el, CAMERA_RADIUS, FOV_DEG, resolution, resolution), az, el


def render_rgba(gaussians: Gaussians, cameras: Cameras, backend: str) -> np.ndarray:
    """Straight-alpha uint8 RGBA [C, H, W, 4] of ``gaussians`` seen by ``cameras``."""
    from physgm.render import rasterize_gaussians

    rgb, alpha, _ = rasterize_gaussians(
        gaussians,
        cameras.viewmats,
        cameras.Ks,
        cameras.width,
        cameras.height,
        background=None,
        backend=backend,
        num_threads=_RENDER_THREADS,
    )
    return to_rgba8(rgb, alpha)


def generate_asset(cfg: SynthConfig, index: int, out: Path) -> str:
    """Generate asset ``index`` into ``out``; returns "done" or "skipped" (already finished)."""
    aid = asset_id(index)
    if (out / aid).is_dir():
        return "skipped"
    plan = plan_asset(cfg, index)
    rng_phys, rng_obj, rng_ann, rng_video = np.random.SeedSequence([cfg.seed, index, 1]).spawn(4)
    physics = sample_physics(plan.material, np.random.default_rng(rng_phys))
    obj = make_object(
        plan.family,
        physics,
        cfg.gaussians,
        np.random.default_rng(rng_obj),
        cfg.photo_textures,
        cfg.varied_light,
    )
    ann = annotate(plan.material, physics.E, physics.nu, np.random.default_rng(rng_ann), cfg.annotator)
    cameras, az, el = view_cameras(cfg.resolution)
    with torch.no_grad():
        rgba = render_rgba(obj.gaussians, cameras, cfg.backend)
    physical = {
        "material": physics.material,
        "E": physics.E,
        "nu": physics.nu,
        "density": physics.density,
        "constitutive_model": constitutive_model(physics.material),
        "annotation": ann.to_json(),
        "source": "synthetic",
        "shape_family": plan.family,
        "cues": {"stiffness": physics.stiffness, "poisson": physics.poisson, "gloss": obj.gloss},
        "generator": {"seed": cfg.seed, "index": index, "version": GENERATOR_VERSION},
    }
    with atomic_asset_dir(out, aid) as tmp:
        write_views_cameras_physics(tmp, rgba, cameras, az, el, physical)
        if cfg.gaussians_file:
            write_ply(obj.gaussians, tmp / "gaussians.ply")
        if plan.video:
            from physgm.data.video import write_reference_video

            write_reference_video(
                tmp, obj.gaussians, physics, np.random.default_rng(rng_video), cfg.resolution, cfg.backend
            )
    return "done"


def write_splits(cfg: SynthConfig, out: Path) -> dict[str, int]:
    """Write ``splits/*.txt`` for every finished asset; returns the size of each split."""
    lists: dict[str, list[str]] = {s: [] for s in SPLITS}
    for i in range(cfg.count):
        if (out / asset_id(i)).is_dir():
            lists[plan_asset(cfg, i).split].append(asset_id(i))
    (out / SPLITS_DIR).mkdir(parents=True, exist_ok=True)
    for split, ids in lists.items():
        (out / SPLITS_DIR / f"{split}.txt").write_text("".join(f"{a}\n" for a in ids))
    return {s: len(v) for s, v in lists.items()}


def _check_config(cfg: SynthConfig, out: Path) -> None:
    """Refuse to resume into a folder made with other settings (the assets would not match)."""
    path = out / CONFIG_FILE
    mine = cfg.to_json()
    if path.is_file():
        theirs = {**_ADDED_SINCE, **json.loads(path.read_text())}
        diff = sorted(k for k in set(mine) | set(theirs) if k != "count" and mine.get(k) != theirs.get(k))
        if diff:
            raise SystemExit(
                f"{out} was generated with other settings ({', '.join(diff)} differ, see {path}); use a new "
                "--out or the same settings"
            )
    write_json(path, mine)


def _worker_init(render_threads: int = 1) -> None:
    global _RENDER_THREADS
    # One thread per process: parallel over assets. Every pixel is computed by one thread
    # whatever the count, so the bytes do not depend on it.
    torch.set_num_threads(1)
    _RENDER_THREADS = render_threads


def _pool_worker_init() -> None:
    """``_worker_init`` for a pool worker, which also stops when the generating process is killed.

    Otherwise it would finish its asset (up to about 30 s with a video) and write it into a folder
    that the user may have deleted and started again with other settings.
    """
    _worker_init()
    threading.Thread(target=_stop_with_parent, args=(os.getppid(),), daemon=True).start()


def _stop_with_parent(parent: int, poll_s: float = 0.5) -> None:
    while os.getppid() == parent:  # a dead parent's children are handed to another process
        time.sleep(poll_s)
    os._exit(1)


def _work(args: tuple[SynthConfig, int, Path]) -> tuple[int, str, str]:
    cfg, index, out = args
    try:
        return index, generate_asset(cfg, index, out), ""
    except Exception:  # report every failed asset at the end instead of killing the pool
        return index, "failed", traceback.format_exc()


def generate(cfg: SynthConfig, out: str | os.PathLike, workers: int = 1, progress: bool = True) -> dict:
    """Generate (or finish) a data set; returns the run summary printed by the CLI."""
    from tqdm import tqdm

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    _check_config(cfg, out)
    jobs = [(cfg, i, out) for i in range(cfg.count)]
    counts = {"done": 0, "skipped": 0, "failed": 0}
    failures: dict[int, str] = {}
    start = time.perf_counter()
    bar = tqdm(total=len(jobs), desc="assets", disable=not progress, unit="asset")
    if workers <= 1:
        threads = torch.get_num_threads()
        _worker_init(render_threads=2)
        try:
            results = (_work(j) for j in jobs)
            for index, status, err in results:
                counts[status] += 1
                failures.update({index: err} if err else {})
                bar.update()
        finally:
            torch.set_num_threads(threads)
    else:
        with mp.get_context("spawn").Pool(workers, initializer=_pool_worker_init) as pool:
            for index, status, err in pool.imap_unordered(_work, jobs):
                counts[status] += 1
                failures.update({index: err} if err else {})
                bar.update()
    bar.close()
    seconds = time.perf_counter() - start
    splits = write_splits(cfg, out)
    for stale in out.glob(f"{TMP_PREFIX}*"):
        print(
            f"warning: left-over temporary folder {stale} (an asset failed or was interrupted)",
            file=sys.stderr,
        )
    return {
        **counts,
        "seconds": round(seconds, 2),
        "assets_per_min": round(60 * counts["done"] / seconds, 2) if counts["done"] else 0.0,
        "splits": splits,
        "failures": {asset_id(i): e.strip().splitlines()[-1] for i, e in failures.items()},
        "_tracebacks": failures,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m physgm.data.synth", description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, required=True, help="data set root (created; resumed if it exists)")
    p.add_argument("--count", type=int, required=True, help="number of assets")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resolution", type=int, default=128, help="square view size in pixels")
    p.add_argument("--gaussians", type=int, default=8000, help="Gaussians per object")
    p.add_argument("--workers", type=int, default=1, help="processes (one torch thread each)")
    p.add_argument(
        "--video-fraction", type=float, default=0.2, help="share of assets with a reference drop video"
    )
    p.add_argument(
        "--backend", default="warp", help="renderer backend: warp, torch (slow reference), gsplat (CUDA)"
    )
    p.add_argument("--materials", default=None, help="comma-separated subset of materials")
    p.add_argument("--families", default=None, help="comma-separated subset of shape families")
    p.add_argument(
        "--label-noise",
        type=float,
        default=None,
        help="annotator: chance E and nu move to a neighbouring category",
    )
    p.add_argument(
        "--material-confusion",
        type=float,
        default=None,
        help="annotator: chance of a look-alike material label",
    )
    p.add_argument(
        "--annotator-config", type=Path, default=None, help="JSON or YAML file with AnnotatorConfig fields"
    )
    p.add_argument(
        "--photo-textures",
        type=float,
        default=0.0,
        help="chance an asset wears a photographed material texture",
    )
    p.add_argument(
        "--varied-light", action="store_true", help="a random light per asset instead of the fixed one"
    )
    p.add_argument(
        "--no-gaussians-file",
        action="store_true",
        help="skip each asset's gaussians.ply, two thirds of its bytes: training reads only the views; "
        "the volume bench, surface loss and DPO on the asset's own Gaussians need it",
    )
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)

    ann = {}
    if a.annotator_config is not None:
        import yaml

        ann = yaml.safe_load(a.annotator_config.read_text()) or {}
    if a.label_noise is not None:
        ann.update(p_neighbour_E=a.label_noise, p_neighbour_nu=a.label_noise)
    if a.material_confusion is not None:
        ann["p_material"] = a.material_confusion

    def split(s: str | None) -> list[str] | None:
        return None if s is None else [x.strip() for x in s.split(",") if x.strip()]

    cfg = SynthConfig(
        count=a.count,
        seed=a.seed,
        resolution=a.resolution,
        gaussians=a.gaussians,
        video_fraction=a.video_fraction,
        backend=a.backend,
        materials=split(a.materials),
        families=split(a.families),
        photo_textures=a.photo_textures,
        varied_light=a.varied_light,
        gaussians_file=not a.no_gaussians_file,
        annotator=AnnotatorConfig.from_dict(ann),
    )
    summary = generate(cfg, a.out, workers=a.workers, progress=not a.no_progress)
    for i, tb in summary.pop("_tracebacks").items():
        print(f"asset {asset_id(i)} failed:\n{tb}", file=sys.stderr)
    print(
        f"generated {summary['done']} assets ({summary['skipped']} already there, "
        f"{summary['failed']} failed) in {summary['seconds']:.1f} s: "
        f"{summary['assets_per_min']:.1f} assets/min"
    )
    print(json.dumps(summary))
    return 1 if summary["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
