"""Frozen-encoder features of a data set's input views, computed once and stored beside it.

The CPU default encoder (frozen ImageNet MobileNetV2, ``physgm.model.cnn_encoder``) has no
trainable parameter, so its outputs for a view never change: a training step that reads them
from disk skips the encoder. The input views of every asset are the ring at the input elevation
(``physgm.data.views``), so only those views are cached, all of them, which keeps
``random_azimuth`` working.

Layout: ``<root>/features/<name>/meta.json`` + one ``<asset_id>.npz`` per asset, where
``<name>`` encodes a ``CacheKey``: the encoder, the sha256 of its weights file, the input
resolution and the background the views are composited over, and, when the data set stores its
views larger than the input, the resolution the ImageNet classifier reads them at (it sees more
of an object's identity there; ``physgm.model.cnn_encoder``). Change any of them and a new
folder is built; the old one is left for the user to delete. Pixel augmentations would make a
cache wrong: physgm's training has none (its only randomness is which views and targets are
drawn), so none is dropped. Two processes that build one folder take turns (``build_lock``), and
the second finds the first's assets done.

    python -m physgm.data.feature_cache ROOT [--resolution 128] [--splits train,val,test,dpo]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from functools import cache
from pathlib import Path

import numpy as np
import torch

from physgm.data.format import SPLITS, AssetError, evenly_spaced, load_asset, read_split
from physgm.data.views import composite_views, ring_views
from physgm.model.cnn_encoder import ImageFeatures, MobileNetEncoder
from physgm.model.pretrained import mobilenet_v2_weights_path

CACHE_VERSION = 1
FEATURES_DIR = "features"
_FIELDS = ("s4", "s8", "s16", "s32", "imagenet_logits")


@dataclass(frozen=True)
class CacheKey:
    """Everything that changes the cached numbers."""

    encoder: str  # encoder kind, "mobilenet_v2"
    weights_sha256: str  # of the weights file the encoder was loaded from
    resolution: int  # px, square input views
    background: float  # grey level the RGBA views are composited over
    input_elevation_deg: float = 0.0  # the ring of views that is cached
    version: int = CACHE_VERSION
    classifier_resolution: int | None = None  # px the classifier reads the views at; None: the input's

    @property
    def name(self) -> str:
        # A field at None is left out, so keys from before it existed keep their folder.
        fields = {k: v for k, v in asdict(self).items() if v is not None}
        digest = hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:12]
        return f"{self.encoder}-{self.resolution}px-{digest}"


@cache
def file_sha256(path: str) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def mobilenet_key(
    resolution: int,
    background: float,
    weights: str | None = None,
    input_elevation_deg: float = 0.0,
    stored_resolution: int | None = None,
) -> CacheKey:
    """The key of MobileNetV2 features (``weights``: default the packaged file).

    ``stored_resolution``: the side of the data set's stored views (``stored_view_size``); when
    it exceeds ``resolution`` the classifier reads the views at that size.
    """
    path = str(weights) if weights else str(mobilenet_v2_weights_path())
    classifier = int(stored_resolution) if stored_resolution and stored_resolution > resolution else None
    return CacheKey(
        "mobilenet_v2",
        file_sha256(path),
        int(resolution),
        float(background),
        float(input_elevation_deg),
        classifier_resolution=classifier,
    )


def stored_view_size(root: str | Path, splits: tuple[str, ...] = SPLITS) -> int | None:
    """The larger side of the first view of the first asset in ``splits`` (None: no asset)."""
    root = Path(root)
    for s in splits:
        if (root / "splits" / f"{s}.txt").exists():
            for aid in read_split(root, s):
                try:
                    cams = load_asset(root / aid).cameras
                except AssetError:
                    continue
                return int(max(cams.width, cams.height))
    return None


def cache_dir(root: str | Path, key: CacheKey) -> Path:
    return Path(root) / FEATURES_DIR / key.name


def _save_atomic(path: Path, arrays: dict[str, np.ndarray]) -> None:
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)


@contextmanager
def build_lock(folder: Path, log) -> Iterator[None]:
    """Hold ``<folder>/.lock`` while building, so two processes never compute the same assets.

    A second builder (an evaluation started while ``python -m physgm.data.feature_cache`` runs,
    say) waits, then finds the assets done. The lock is ``flock``'s, so it goes with its process
    if that dies; where ``fcntl`` is missing (Windows) builders do not wait, which wastes time but
    corrupts nothing, since every file is written atomically.
    """
    try:
        import fcntl
    except ImportError:
        yield
        return
    with open(folder / ".lock", "a") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log(f"feature cache: another process is building {folder}; waiting for it")
            fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def build_feature_cache(
    root: str | Path,
    key: CacheKey,
    splits: tuple[str, ...] = SPLITS,
    encoder: MobileNetEncoder | None = None,
    log=None,
    max_assets: int | None = None,
) -> Path:
    """Compute and store the features of every asset in ``splits`` that has none yet; returns the folder.

    ``max_assets``: only the evenly spaced subset of each split that a dataset with that many
    assets reads (``format.evenly_spaced``)."""
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))  # stdout is for JSON reports
    root = Path(root)
    out = cache_dir(root, key)
    out.mkdir(parents=True, exist_ok=True)
    meta = out / "meta.json"
    if not meta.exists():
        tmp = meta.with_name(".meta.json.tmp")
        tmp.write_text(json.dumps(asdict(key), indent=1))
        os.replace(tmp, meta)
    listed = [s for s in splits if (root / "splits" / f"{s}.txt").exists()]
    ids = sorted({a for s in listed for a in evenly_spaced(read_split(root, s), max_assets)})
    if all((out / f"{a}.npz").exists() for a in ids):
        return out
    with build_lock(out, log):
        # Listed under the lock: the assets a builder that held it before us wrote are done.
        todo = [a for a in ids if not (out / f"{a}.npz").exists()]
        if todo:
            _compute(root, out, key, todo, encoder, log)
    return out


def _compute(root: Path, out: Path, key: CacheKey, todo: list[str], encoder, log) -> None:
    """Encode the ring views of each asset in ``todo`` and write its ``.npz``."""
    if encoder is None:
        weights = None  # the packaged file; a CacheKey from another file needs that encoder passed in
        encoder = MobileNetEncoder(weights)
    start = time.perf_counter()
    for n, aid in enumerate(todo, 1):
        try:
            asset = load_asset(root / aid)
        except AssetError as err:
            log(f"feature cache: skipping malformed asset {aid}: {err}")
            continue
        views = ring_views(asset.cameras.c2w, key.input_elevation_deg)
        rgba = asset.load_rgba(views)
        images, _, _ = composite_views(rgba, asset.cameras.Ks[views], key.resolution, key.background)
        classifier_images = None
        if key.classifier_resolution is not None:
            classifier_images, _, _ = composite_views(
                rgba, asset.cameras.Ks[views], key.classifier_resolution, key.background
            )
        feats = encoder.encode(images, classifier_images)
        arrays = {name: getattr(feats, name).numpy().astype(np.float16) for name in _FIELDS}
        _save_atomic(out / f"{aid}.npz", {"views": np.asarray(views, dtype=np.int64), **arrays})
        if n % 100 == 0 or n == len(todo):
            log(f"feature cache: {n}/{len(todo)} assets, {time.perf_counter() - start:.0f} s ({out})")


class FeatureStore:
    """Reads cached features of chosen views of an asset."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        if not (self.folder / "meta.json").exists():
            raise FileNotFoundError(
                f"{self.folder} is not a feature cache (no meta.json); build it with python -m "
                f"physgm.data.feature_cache"
            )

    def load(self, asset_id: str, views: list[int] | None = None) -> ImageFeatures:  # [V, ...] float16
        """The cached features of ``views`` (indices into the asset's cameras; None: every cached view)."""
        path = self.folder / f"{asset_id}.npz"
        if not path.exists():
            raise FileNotFoundError(
                f"no cached features for asset {asset_id} in {self.folder}; rebuild the cache"
            )
        with np.load(path) as data:
            stored = [int(v) for v in data["views"]]
            views = stored if views is None else views
            missing = [v for v in views if v not in stored]
            if missing:
                raise ValueError(
                    f"views {missing} of asset {asset_id} are not cached (cached: {stored}); "
                    "the cache holds the input-elevation ring only"
                )
            rows = [stored.index(v) for v in views]
            return ImageFeatures(**{name: torch.from_numpy(data[name][rows]) for name in _FIELDS})


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("root", type=Path)
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--background", type=float, default=1.0)
    p.add_argument("--splits", default=",".join(SPLITS))
    args = p.parse_args(argv)
    if not (args.root / "splits").is_dir():
        print(f"error: {args.root} has no splits/ folder; is it a PhysAssets data set?", file=sys.stderr)
        return 2
    key = mobilenet_key(args.resolution, args.background, stored_resolution=stored_view_size(args.root))
    out = build_feature_cache(args.root, key, tuple(s for s in args.splits.split(",") if s))
    print(json.dumps({"cache": str(out), "key": asdict(key), "assets": len(list(out.glob("*.npz")))}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
