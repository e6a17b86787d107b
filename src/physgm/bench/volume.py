"""How much body the simulator gets from the model's Gaussians; prints one JSON object.

    python -m physgm.bench volume CKPT --data data/synthetic_photo_g24 [--split val] [--views 1]
                                       [--assets 64] [--min-opacity 0.05 0.02]

``simulate`` fills the Gaussians it keeps (opacity at least ``planner.min_opacity``) with particles
(``sampling.sample_particles``), so the simulated body has the volume of what those Gaussians
enclose. Per asset of the split, this compares that volume for the model's Gaussians (the fixed
evaluation inputs of ``physgm.train.evaluate``, 1 or 4 views) with the volume the asset's own
Gaussians (its gaussians.ply, all of them) enclose, both on the lattice the planner would use for
the asset's true extent (``planner.choose_spacing``: 24 particles across at its defaults). The
report gives, per threshold, the median, p10 and p90 of predicted / true volume over the opaque
assets and over the translucent ones (whose own Gaussians' median opacity is under
``TRANSLUCENT``: glass, jelly), and the opaque assets' median per material. The row ``planner``
uses, per asset, the threshold ``simulate`` picks (``sampling.mass_opacity`` at the planner's
defaults: 0.05, lower for an object whose Gaussians are all faint). A ratio of 1 means the
simulated body weighs what the object does.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from physgm.bench.model_split import check_model_and_split
from physgm.errors import UserError
from physgm.gaussians import Gaussians, read_ply
from physgm.physics.materials import MATERIAL_NAMES
from physgm.sim.planner import PlannerConfig, choose_spacing
from physgm.sim.sampling import mass_opacity, sample_particles

TRANSLUCENT = 0.1  # an asset whose own Gaussians are fainter than this (median) is translucent


def enclosed_volume(gaussians: Gaussians, spacing: float, min_opacity: float) -> float:
    """m^3 (model units^3) of the particles ``simulate`` would fill ``gaussians`` with; 0 if none
    is as opaque as ``min_opacity``."""
    if not bool((gaussians.opacities >= min_opacity).any()):
        return 0.0
    return len(sample_particles(gaussians, spacing, min_opacity)) * spacing**3


def _summary(ratios: list[float]) -> dict:
    if not ratios:
        return {"assets": 0}
    p10, median, p90 = np.percentile(ratios, [10, 50, 90])
    return {"assets": len(ratios), "median": float(median), "p10": float(p10), "p90": float(p90)}


def volume_report(
    model, resolution: int, root: str, split: str, views: int, assets: int, thresholds: list[float]
) -> dict:
    """The report of the module docstring for ``model`` reading ``resolution`` px views."""
    from physgm.train.evaluate import view_datamodule

    data = view_datamodule(model, root, split, views, resolution)
    data.setup("test")
    planner = PlannerConfig()
    rows = []
    with torch.no_grad():
        for batch in data.test_dataloader():
            out = model(batch.images, batch.masks, batch.c2w, batch.Ks, batch.features)
            for i, asset in enumerate(batch.asset_ids):
                if len(rows) == assets:
                    break
                own = Path(root) / asset / "gaussians.ply"
                if not own.is_file():
                    raise UserError(
                        f"{own} not found: bench volume compares the model's Gaussians with the asset's "
                        "own, which a synthetic set has (python -m physgm.data.synth); real-object sets "
                        "have none"
                    )
                truth = read_ply(own, keep_sh=False)
                extent = float((truth.means.amax(0) - truth.means.amin(0)).max())
                spacing = choose_spacing(extent, planner)[1]  # the planner's lattice
                true_volume = enclosed_volume(truth, spacing, 0.0)
                pred = out.gaussians.to_gaussians(i).detach()
                chosen = mass_opacity(pred.opacities, planner.min_opacity, planner.relative_opacity)
                ratio = {str(t): enclosed_volume(pred, spacing, t) / true_volume for t in thresholds}
                ratio["planner"] = enclosed_volume(pred, spacing, chosen) / true_volume
                rows.append(
                    {
                        "asset": asset,
                        "material": MATERIAL_NAMES[int(batch.true_material[i])],
                        "translucent": float(truth.opacities.median()) < TRANSLUCENT,
                        "ratio": ratio,
                    }
                )
            if len(rows) == assets:
                break
    report: dict = {"data": root, "split": split, "views": views, "assets": len(rows), "thresholds": {}}
    for t in [*map(str, thresholds), "planner"]:
        by_material = defaultdict(list)
        for r in rows:
            if not r["translucent"]:
                by_material[r["material"]].append(r["ratio"][t])
        report["thresholds"][t] = {
            "opaque": _summary([r["ratio"][t] for r in rows if not r["translucent"]]),
            "translucent": _summary([r["ratio"][t] for r in rows if r["translucent"]]),
            "opaque_median_by_material": {m: float(np.median(v)) for m, v in sorted(by_material.items())},
        }
    return report


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(prog="python -m physgm.bench volume", description=__doc__.split("\n")[0])
    p.add_argument("ckpt", type=Path, help="PhysGM checkpoint")
    p.add_argument("--data", required=True, type=Path, help="a PhysAssets root with splits/ (synthetic)")
    p.add_argument("--split", default="val")
    p.add_argument("--views", type=int, default=1, choices=[1, 4])
    p.add_argument("--assets", type=int, default=64, help="at most this many of the split's assets")
    p.add_argument("--min-opacity", type=float, nargs="+", default=[0.05], help="thresholds to compare")
    a = p.parse_args(argv)
    check_model_and_split(a.ckpt, a.data, a.split, "python -m physgm.data.synth --out ROOT")
    if a.assets < 1 or any(not 0 <= t < 1 for t in a.min_opacity):
        raise UserError("--assets must be >= 1 and every --min-opacity in [0, 1)")
    from physgm.model.checkpoint import input_size, load_model

    model, ckpt = load_model(a.ckpt, "cpu")
    model.eval()
    res = input_size(model, ckpt.hparams)
    report = {
        "ckpt": str(a.ckpt),
        **volume_report(model, res, str(a.data), a.split, a.views, a.assets, a.min_opacity),
    }
    print(json.dumps(report, indent=1))
    return report
