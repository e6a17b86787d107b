"""One training root over several data sets, by links, without copying a file.

Each source's assets appear in the new root as ``<source folder name>--<asset id>``, a relative
symbolic link to the asset's folder, so two generated sets whose ids repeat (every ``synth`` run
numbers from ``syn_000000``) sit side by side. Each split list is the union of the sources'.
A feature cache (``physgm.data.feature_cache``) that every source has built under the same key
is linked too, asset by asset, so training on the new root reads the cached features; a cache
that some source lacks is left out, and ``feature_cache`` builds it in the new root on first
use.

The new root is written beside, under a temporary name, and renamed into place when complete:
an interrupted run leaves no half-made root under the requested name.

    python -m physgm.data.combine OUT SRC [SRC ...]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

from physgm.data.feature_cache import FEATURES_DIR
from physgm.data.format import SPLITS, SPLITS_DIR, read_split
from physgm.errors import UserError

SEPARATOR = "--"


def combine(out: str | os.PathLike, sources: list[str | os.PathLike]) -> dict:
    """Write the combined root ``out`` over ``sources``; returns a summary (assets per split, caches)."""
    out = Path(out)
    srcs = [Path(s) for s in sources]
    _check(out, srcs)
    tmp = out.with_name(f".{out.name}.partial")
    if tmp.exists():
        shutil.rmtree(tmp)  # left by an interrupted run
    tmp.mkdir(parents=True)
    try:
        summary = _write(tmp, out, srcs)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return summary


def _check(out: Path, srcs: list[Path]) -> None:
    if out.exists():
        raise UserError(f"{out} exists; choose a new folder for the combined root, or delete it first")
    if len(srcs) < 2:
        raise UserError(f"combine needs at least two data sets, got {len(srcs)}")
    names = [s.resolve().name for s in srcs]
    if len(set(names)) != len(names):
        raise UserError(f"the data sets' folder names prefix their asset ids and must differ: {names}")
    for s in srcs:
        if not (s / SPLITS_DIR).is_dir():
            raise UserError(f"{s} is not a data set (no {SPLITS_DIR}/ folder); give the folders synth wrote")


def _write(tmp: Path, out: Path, srcs: list[Path]) -> dict:
    base = out.parent.resolve() / out.name  # where the links will live; relative targets start there
    prefixes = {s: s.resolve().name + SEPARATOR for s in srcs}
    ids = {s: set() for s in srcs}  # each source's asset ids over every split
    splits = {}
    (tmp / SPLITS_DIR).mkdir()
    for split in SPLITS:
        listing = [s for s in srcs if (s / SPLITS_DIR / f"{split}.txt").is_file()]
        if not listing:
            continue
        lines = []
        for s in listing:
            own = read_split(s, split)
            lines += [prefixes[s] + aid for aid in own]
            ids[s].update(own)
        # written even when empty, as the sources list it
        (tmp / SPLITS_DIR / f"{split}.txt").write_text("".join(f"{line}\n" for line in lines))
        splits[split] = len(lines)
    for s in srcs:
        for aid in sorted(ids[s]):
            if not (s / aid).is_dir():
                raise UserError(f"{s / SPLITS_DIR} lists {aid}, which has no folder in {s}")
            (tmp / f"{prefixes[s]}{aid}").symlink_to(os.path.relpath((s / aid).resolve(), base))
    caches = _link_caches(tmp, base, srcs, prefixes, ids)
    return {"root": str(out), "assets": sum(len(v) for v in ids.values()), "splits": splits, "caches": caches}


def _link_caches(tmp: Path, base: Path, srcs: list[Path], prefixes: dict, ids: dict) -> list[str]:
    """Feature caches every source holds with the same meta.json: linked asset by asset."""
    folders = [{f.name: f for f in (s / FEATURES_DIR).glob("*") if (f / "meta.json").is_file()} for s in srcs]
    linked = []
    for name in sorted(set.intersection(*(set(f) for f in folders))):
        metas = {json.dumps(json.loads((f[name] / "meta.json").read_text()), sort_keys=True) for f in folders}
        if len(metas) != 1:
            continue
        dest = tmp / FEATURES_DIR / name
        dest.mkdir(parents=True)
        shutil.copyfile(folders[0][name] / "meta.json", dest / "meta.json")
        for s, f in zip(srcs, folders, strict=True):
            for aid in sorted(ids[s]):
                npz = f[name] / f"{aid}.npz"
                if npz.is_file():
                    (dest / f"{prefixes[s]}{aid}.npz").symlink_to(
                        os.path.relpath(npz.resolve(), base / FEATURES_DIR / name)
                    )
        linked.append(name)
    return linked


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m physgm.data.combine", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("out", help="the combined root to create (must not exist)")
    parser.add_argument("sources", nargs="+", help="data set folders (each with splits/)")
    args = parser.parse_args(argv)
    try:
        summary = combine(args.out, args.sources)
    except UserError as exc:
        print(f"combine: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
