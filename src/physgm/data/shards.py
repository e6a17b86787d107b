"""litdata shards of a PhysAssets folder, for streaming to many nodes.

    python -m physgm.data.shards --root data/synthetic --out data/synthetic_shards [--workers 2]

writes ``<out>/<split>/`` for every split (litdata chunks + index.json). One sample per
asset: the PNG bytes of all views (undecoded, so shards are as small as the folder) and the
asset's cameras.json and physical.json. ``ShardDataset`` streams them back and cuts examples
with the same code as the folder dataset, so both backends give identical samples.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from pathlib import Path

import numpy as np
import torch
from litdata import StreamingDataset
from PIL import Image

from physgm.data.format import SPLITS, AssetError, load_asset, parse_camera, parse_physical, read_split
from physgm.data.readers import read_camera_dict
from physgm.data.views import LOAD_ERRORS, Example, ViewConfig, build_example, example_rng


def asset_to_sample(path: str) -> dict:
    """One asset folder -> one shard sample (validated first, so shards hold no broken assets)."""
    asset = load_asset(path)
    pngs = [f.read_bytes() for f in asset.view_files]
    offsets = np.cumsum([0] + [len(b) for b in pngs]).astype(np.int64)
    meta = {
        # The cameras as the project's cameras.json object (OpenCV), whatever file the folder holds.
        "cameras": read_camera_dict(asset.path, []),
        "physical": json.loads((asset.path / "physical.json").read_text()),
    }
    return {
        "id": asset.id,
        "meta": json.dumps(meta),
        "views": np.frombuffer(b"".join(pngs), dtype=np.uint8).copy(),
        "offsets": offsets,
    }


def write_shards(
    root: str | Path,
    out: str | Path,
    splits: tuple[str, ...] = SPLITS,
    chunk_bytes: str = "64MB",
    workers: int = 1,
    start_method: str | None = None,
) -> dict[str, int]:
    """Write ``out/<split>/`` shards for each split; returns the number of assets per split.

    ``start_method`` defaults to "fork" on Linux: the workers only read files (no torch or Warp
    work), and a spawned worker would spend ~10 s re-importing the package.
    """
    if start_method is None:
        start_method = "fork" if sys.platform.startswith("linux") else "spawn"
    from litdata import optimize

    root, counts = Path(root), {}
    for split in splits:
        ids = read_split(root, split)
        counts[split] = len(ids)
        if not ids:
            continue
        optimize(
            fn=asset_to_sample,
            inputs=[str(root / a) for a in ids],
            output_dir=str(Path(out) / split),
            chunk_bytes=chunk_bytes,
            num_workers=workers,
            mode="overwrite",
            verbose=False,
            start_method=start_method,
        )
    return counts


class ShardRecord:
    """A shard sample seen through the ``AssetRecord`` protocol."""

    def __init__(self, sample: dict):
        self.id = str(sample["id"])
        meta = json.loads(sample["meta"])
        problems: list[str] = []
        cams = [
            parse_camera(fr, f"{self.id} camera {i}", problems)
            for i, fr in enumerate(meta["cameras"]["frames"])
        ]
        self.physical = parse_physical(meta["physical"], problems)
        if problems:
            raise AssetError(f"shard sample {self.id} is malformed: {'; '.join(problems)}")
        self.c2w = torch.tensor(np.stack([c[0] for c in cams]), dtype=torch.float32)
        self.Ks = torch.tensor(np.stack([c[1] for c in cams]), dtype=torch.float32)
        self.width, self.height = cams[0][2], cams[0][3]
        self._views = np.asarray(sample["views"], dtype=np.uint8)
        self._offsets = np.asarray(sample["offsets"], dtype=np.int64)

    def load_rgba(self, indices: list[int]) -> np.ndarray:
        out = []
        for i in indices:
            data = self._views[self._offsets[i] : self._offsets[i + 1]].tobytes()
            with Image.open(io.BytesIO(data)) as im:
                out.append(np.asarray(im.convert("RGBA")))
        return np.stack(out).astype(np.float32) / 255.0

    def load_surface(self) -> None:  # the shards do not carry gaussians.ply
        return None


class ShardDataset(StreamingDataset):
    """Streams one split's shards and yields ``(Example | None, skipped ids)`` like ``FolderDataset``."""

    def __init__(
        self,
        input_dir: str,
        views: ViewConfig,
        deterministic: bool,
        shuffle: bool = False,
        on_corrupt: str = "raise",
        seed: int = 0,
        **kwargs,
    ):
        super().__init__(input_dir, shuffle=shuffle, seed=seed, **kwargs)
        self.views, self.deterministic, self.on_corrupt, self.example_seed = (
            views,
            deterministic,
            on_corrupt,
            seed,
        )

    def __getitem__(self, index) -> tuple[Example | None, list[str]]:
        sample = super().__getitem__(index)
        try:
            record = ShardRecord(sample)
            return build_example(
                record, self.views, example_rng(record.id, self.deterministic, self.example_seed)
            ), []
        except LOAD_ERRORS as err:
            if self.on_corrupt == "raise":
                raise AssetError(f"shard sample {sample.get('id')} could not be loaded: {err}") from err
            return None, [str(sample.get("id"))]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m physgm.data.shards", description="Write litdata shards of a PhysAssets folder."
    )
    p.add_argument("--root", type=Path, required=True, help="PhysAssets folder with splits/")
    p.add_argument("--out", required=True, help="output folder (or cloud URL litdata can write to)")
    p.add_argument("--splits", default=",".join(SPLITS), help="comma-separated splits")
    p.add_argument("--chunk-bytes", default="64MB")
    p.add_argument("--workers", type=int, default=1)
    a = p.parse_args(argv)
    counts = write_shards(a.root, a.out, tuple(s for s in a.splits.split(",") if s), a.chunk_bytes, a.workers)
    print(json.dumps({"out": a.out, "assets": counts}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
