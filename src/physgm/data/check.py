"""Validate a PhysAssets folder: ``python -m physgm.data.check ROOT [--json] [--workers 2]``.

Reports every malformed asset in one pass (never stops at the first): missing or unreadable
views, views of the wrong size or fully transparent, non-finite or non-rigid cameras,
impossible physics (E <= 0, nu outside (-1, 0.5)), unknown materials, annotation values that
are not categories, unreadable Gaussians, videos without metadata or with the wrong frame
count, and split lists naming missing assets or putting one asset in two splits.
Exit code 0 when the data set is clean, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from physgm.data.format import SPLITS, SPLITS_DIR, read_asset, read_cameras
from physgm.data.writer import TMP_PREFIX


@dataclass
class Report:
    """Problems per asset id, plus data set level problems (splits, left-over folders)."""

    assets: dict[str, list[str]] = field(default_factory=dict)  # only assets with problems
    dataset: list[str] = field(default_factory=list)
    checked: int = 0

    @property
    def ok(self) -> bool:
        return not self.assets and not self.dataset

    def to_json(self) -> dict:
        return {
            "ok": self.ok,
            "checked": self.checked,
            "bad_assets": len(self.assets),
            "assets": self.assets,
            "dataset": self.dataset,
        }


def _check_view(path: Path, size: tuple[int, int]) -> str | None:
    try:
        with Image.open(path) as im:
            im.load()
            mode, (w, h) = im.mode, im.size
            alpha = np.asarray(im.getchannel("A")) if "A" in im.getbands() else None
    except Exception as err:  # PIL raises many types for truncated or foreign files
        return f"{path.parent.name}/{path.name} is unreadable ({type(err).__name__}: {err})"
    if (w, h) != size:
        return f"{path.parent.name}/{path.name} is {w}x{h} but cameras.json says {size[0]}x{size[1]}"
    if alpha is None:
        return f"{path.parent.name}/{path.name} has no alpha channel (mode {mode}); views must be RGBA"
    if alpha.max() == 0:
        return f"{path.parent.name}/{path.name} is fully transparent (the object is not in view)"
    return None


def _check_video(path: Path, frames: int, size: tuple[int, int]) -> str | None:
    import imageio_ffmpeg

    try:
        reader = imageio_ffmpeg.read_frames(str(path))
        meta = next(reader)
        count = sum(1 for _ in reader)
    except Exception as err:  # ffmpeg failures surface as several exception types
        return f"videos/{path.name} is unreadable ({type(err).__name__}: {err})"
    if tuple(meta["size"]) != size:
        return (
            f"videos/{path.name} is {meta['size'][0]}x{meta['size'][1]} but its json says {size[0]}x{size[1]}"
        )
    if count != frames:
        return f"videos/{path.name} has {count} frames but its json says {frames}"
    return None


def check_asset(path: str | Path, deep: bool = True) -> list[str]:
    """Every problem of one asset folder (empty list when it is fine).

    Args:
        path: the asset folder.
        deep: also decode every view, the Gaussians and the videos (slower).
    """
    path = Path(path)
    asset, problems = read_asset(path)
    if not deep:
        return problems
    # Views are checked even when physical.json is broken, so one pass shows everything.
    cam_problems: list[str] = []
    cams = read_cameras(path, cam_problems)
    if cams is not None:
        cameras, files = cams[0], cams[1]
        for f in files:
            msg = _check_view(f, (cameras.width, cameras.height))
            if msg:
                problems.append(msg)
    ply = path / "gaussians.ply"
    if ply.exists():
        from physgm.gaussians import read_ply

        try:
            if len(read_ply(ply)) == 0:
                problems.append("gaussians.ply holds no Gaussians")
        except Exception as err:
            problems.append(f"gaussians.ply: {err}")
    if asset is not None:
        for video in asset.videos:
            msg = _check_video(video.path, video.frames, (video.cameras.width, video.cameras.height))
            if msg:
                problems.append(msg)
    return problems


def asset_dirs(root: Path) -> list[Path]:
    """Asset folders directly under ``root`` (hidden folders and ``splits`` excluded)."""
    return sorted(
        p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and p.name != SPLITS_DIR
    )


def _check_splits(root: Path, ids: set[str], report: Report) -> None:
    split_dir = root / SPLITS_DIR
    if not split_dir.is_dir():
        report.dataset.append(f"no {SPLITS_DIR}/ folder with {', '.join(s + '.txt' for s in SPLITS)}")
        return
    seen: dict[str, str] = {}
    for split in SPLITS:
        path = split_dir / f"{split}.txt"
        if not path.is_file():
            report.dataset.append(f"missing split list {SPLITS_DIR}/{split}.txt")
            continue
        for line in path.read_text().splitlines():
            aid = line.split("#")[0].strip()
            if not aid:
                continue
            if aid not in ids:
                report.dataset.append(f"{SPLITS_DIR}/{split}.txt names {aid}, which is not an asset folder")
            if aid in seen:
                report.dataset.append(f"{aid} is in both {seen[aid]} and {split}")
            seen.setdefault(aid, split)


def _check_one(args: tuple[Path, bool]) -> tuple[str, list[str]]:
    path, deep = args
    return path.name, check_asset(path, deep)


def check_root(root: str | Path, deep: bool = True, workers: int = 1, progress: bool = False) -> Report:
    """Check every asset under ``root`` and the split lists."""
    from tqdm import tqdm

    root = Path(root)
    report = Report()
    if not root.is_dir():
        report.dataset.append(f"{root} is not a directory")
        return report
    dirs = asset_dirs(root)
    jobs = [(d, deep) for d in dirs]
    if workers > 1:
        with mp.get_context("spawn").Pool(workers) as pool:
            results = list(
                tqdm(pool.imap(_check_one, jobs, chunksize=8), total=len(jobs), disable=not progress)
            )
    else:
        results = [_check_one(j) for j in tqdm(jobs, disable=not progress)]
    for name, problems in results:
        if problems:
            report.assets[name] = problems
    report.checked = len(dirs)
    for stale in sorted(root.glob(f"{TMP_PREFIX}*")):
        report.dataset.append(
            f"left-over temporary folder {stale.name} from an interrupted generation; delete it or resume"
        )
    _check_splits(root, {d.name for d in dirs}, report)
    return report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m physgm.data.check", description="Validate a PhysAssets folder."
    )
    p.add_argument("root", type=Path)
    p.add_argument("--json", action="store_true", help="print one JSON report instead of text")
    p.add_argument("--quick", action="store_true", help="skip decoding views, Gaussians and videos")
    p.add_argument("--workers", type=int, default=1)
    a = p.parse_args(argv)
    report = check_root(
        a.root, deep=not a.quick, workers=a.workers, progress=not a.json and sys.stderr.isatty()
    )
    if a.json:
        print(json.dumps(report.to_json(), indent=1))
    else:
        for aid, problems in report.assets.items():
            print(f"{aid}:")
            for msg in problems:
                print(f"  - {msg}")
        for msg in report.dataset:
            print(f"data set: {msg}")
        status = (
            "OK"
            if report.ok
            else f"{len(report.assets)} malformed asset(s), {len(report.dataset)} data set problem(s)"
        )
        print(f"checked {report.checked} assets under {a.root}: {status}")
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
