"""How deep a one-view reconstruction is: its side silhouette against its front, next to the object's.

    python -m physgm.bench depth CKPT --data data/real_objects [--split val] [--assets 64]

One photo hides an object's depth, and the model has to guess it. Per asset of the split, the model
reads the view at elevation 0 and azimuth 0 the way ``simulate.py`` reads a photo
(``physgm.pipeline.prepared_input``: framed, the canonical camera), and its Gaussians are rendered
from that camera and from azimuth 90 degrees. The width of the side silhouette (alpha 0.5 or more) over
the front's is the depth over the width the model gave the object; the asset's own views at azimuth 0
and 90 give the true one. Each asset's score is predicted over true: 1 is as deep as the object,
under 1 flatter (a ball read as a thick coin scores about 0.5). The report gives every asset's score
and their median, p10 and p90; an asset whose own view shows no silhouette (a faint translucent one)
is skipped, with the reason. Any data set with those two views works, real-object sets included: no
gaussians.ply is needed.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from physgm.bench.model_split import check_model_and_split
from physgm.errors import UserError

SIDE_DEG = 90.0  # azimuth of the side view from the input view
SILHOUETTE_ALPHA = 0.5  # a pixel is inside a silhouette from this alpha


class NoSilhouette(ValueError):
    """An asset's own view shows no silhouette to measure; the report skips it and says why."""


def silhouette_width(alpha: np.ndarray) -> int:
    """Columns of the [H, W] ``alpha`` that hold a pixel of at least ``SILHOUETTE_ALPHA`` (0: none)."""
    cols = np.flatnonzero((alpha >= SILHOUETTE_ALPHA).any(0))
    return int(cols[-1] - cols[0] + 1) if len(cols) else 0


def _view(asset, azimuth: float) -> int | None:
    """Index of the asset's view at elevation 0 and this azimuth, or None."""
    if asset.azimuth_deg is None or asset.elevation_deg is None:
        return None
    off = np.abs((asset.azimuth_deg - azimuth + 180) % 360 - 180)  # degrees, either way round
    hits = np.flatnonzero((np.abs(asset.elevation_deg) < 1e-3) & (off < 1e-3))
    return int(hits[0]) if len(hits) else None


def true_ratio(asset) -> float:
    """Side silhouette width over front silhouette width of the asset's own views at azimuth 0 and 90."""
    front, side = _view(asset, 0.0), _view(asset, SIDE_DEG)
    if front is None or side is None:
        raise UserError(
            f"asset {asset.id} has no views at elevation 0 and azimuth 0 and {SIDE_DEG:g} degrees in its "
            "cameras.json (azimuth_deg, elevation_deg); bench depth needs both, as the synthetic and "
            "real-object sets have them"
        )
    rgba = asset.load_rgba([front, side])
    widths = [silhouette_width(v[..., 3]) for v in rgba]
    if not all(widths):
        raise NoSilhouette(
            f"its view at azimuth 0 or {SIDE_DEG:g} has no pixel of alpha {SILHOUETTE_ALPHA} or more "
            "(a faint translucent object)"
        )
    return widths[1] / widths[0]


def gaussians_ratio(g, size: int) -> float:
    """Side over front silhouette width of Gaussians in the model's frame, seen by the canonical camera
    (azimuth 0) and the side camera (``SIDE_DEG``) at ``size`` px; 0 when the front shows nothing."""
    from physgm.cameras import orbit_cameras
    from physgm.data.format import CAMERA_RADIUS, FOV_DEG
    from physgm.render.api import rasterize_gaussians

    cams = orbit_cameras([0.0, SIDE_DEG], [0.0, 0.0], CAMERA_RADIUS, FOV_DEG, size, size)
    _, alpha, _ = rasterize_gaussians(g, torch.linalg.inv(cams.c2w), cams.Ks, size, size)
    front, side = (silhouette_width(a[..., 0].numpy()) for a in alpha)
    return side / front if front else 0.0


def predicted_ratio(model, size: int, view_file: Path) -> float:
    """``gaussians_ratio`` of the model's Gaussians from one view, read as ``simulate.py`` reads a photo."""
    from physgm.model.predict import predict_scene
    from physgm.pipeline.prepared_input import prepare_input

    inp = prepare_input(view_file, size)
    with torch.no_grad():
        g = predict_scene(model, inp.images, inp.masks, inp.c2w, inp.Ks, inp.classifier_images).gaussians
    return gaussians_ratio(g, 2 * size)


def depth_report(model, size: int, root: Path, split: str, assets: int) -> dict:
    """The report of the module docstring over at most ``assets`` assets of the split, in its order."""
    from physgm.data.format import load_asset, read_split

    rows, skipped = [], {}
    for aid in read_split(root, split)[:assets]:
        asset = load_asset(root / aid)
        try:
            truth = true_ratio(asset)
        except NoSilhouette as err:
            skipped[aid] = str(err)
            continue
        pred = predicted_ratio(model, size, asset.view_files[_view(asset, 0.0)])
        rows.append({"asset": aid, "true": truth, "predicted": pred, "score": pred / truth})
    if not rows:
        raise UserError(f"no asset of split {split!r} of {root} could be measured: {skipped}")
    p10, median, p90 = np.percentile([r["score"] for r in rows], [10, 50, 90])
    return {
        "data": str(root),
        "split": split,
        "assets": len(rows),
        "score": {"median": float(median), "p10": float(p10), "p90": float(p90)},
        "per_asset": rows,
        "skipped": skipped,
    }


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(prog="python -m physgm.bench depth", description=__doc__.split("\n")[0])
    p.add_argument("ckpt", type=Path, help="PhysGM checkpoint")
    p.add_argument("--data", required=True, type=Path, help="a PhysAssets root with splits/")
    p.add_argument("--split", default="val")
    p.add_argument("--assets", type=int, default=64, help="at most this many of the split's assets")
    a = p.parse_args(argv)
    check_model_and_split(
        a.ckpt,
        a.data,
        a.split,
        "python -m physgm.data.synth --out ROOT or python -m physgm.data.real_objects --out ROOT",
    )
    if a.assets < 1:
        raise UserError("--assets must be >= 1")
    from physgm.model.checkpoint import input_size, load_model

    model, ckpt = load_model(a.ckpt, "cpu")
    model.eval()
    size = input_size(model, ckpt.hparams)
    report = {"ckpt": str(a.ckpt), **depth_report(model, size, a.data, a.split, a.assets)}
    print(json.dumps(report, indent=1))
    return report
