"""``python -m physgm.bench stiffness-probe ROOT [ROOT ...]``: how much views say of E within a material.

The generator ties visible cues to where an asset's E lies in its material's range
(``physgm.data.appearance``: a darker tone and a finer texture for a stiffer asset). A model can
read E within a material only if its frozen encoder sees them, so for each data set, over the
assets of its train, val and test splits:

* ``ridge``: a ridge regression from the frozen encoder's pooled features
  (``physics_head.pooled_features``, the procedural expert's input, averaged over the cached views)
  plus a free intercept per material, to the position of log10 E in the material's range, scored by
  ``--folds``-fold cross-validation over the assets: the median abs(log10 E error) in decades and
  the correlation of the predicted with the true position, at each ``--alphas``;
* ``mid_range``: the same error for the guess of the range's middle, which knows the material and
  nothing else;
* ``tone``: per material, Spearman's rank correlation of an asset's brightness (the mean HSV value
  of its object pixels over every fourth view) with its position (negative: stiffer is darker).

It reads the feature cache (``python -m physgm.data.feature_cache ROOT --resolution R``) and
builds it where missing. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from physgm.data.format import load_asset, read_split
from physgm.errors import UserError
from physgm.physics.materials import MATERIAL_NAMES, log10_E_range
from physgm.train.refit_material import pooled_splits


def ridge_cv(
    features: np.ndarray,  # [A, D]
    groups: np.ndarray,  # [A] material index: each gets an unpenalised intercept
    target: np.ndarray,  # [A]
    alpha: float,
    folds: int = 5,
    seed: int = 0,
) -> np.ndarray:  # [A] each asset predicted by the fit on the folds it is not in
    """K-fold ridge regression with per-group intercepts; features standardised on each fold's fit."""
    n = len(target)
    if n < 2 * folds:
        raise UserError(f"the probe needs at least {2 * folds} assets for {folds} folds, got {n}")
    names = np.unique(groups)
    onehot = (groups[:, None] == names[None]).astype(np.float64)
    order = np.random.default_rng(seed).permutation(n)
    pred = np.empty(n)
    for k in range(folds):
        test = order[k::folds]
        fit = np.setdiff1d(order, test)
        mean, std = features[fit].mean(0), features[fit].std(0) + 1e-6
        a = np.concatenate([(features - mean) / std, onehot], 1)
        penalty = np.concatenate([np.full(features.shape[1], alpha), np.full(len(names), 1e-9)])
        w = np.linalg.solve(a[fit].T @ a[fit] + np.diag(penalty), a[fit].T @ target[fit])
        pred[test] = a[test] @ w
    return pred


def brightness(rgba: np.ndarray) -> float:  # [V, H, W, 4] in [0, 1], straight alpha
    """Mean HSV value (the largest of R, G, B) over the pixels with alpha > 0.5 of each view."""
    values = [view[..., :3][view[..., 3] > 0.5].max(1).mean() for view in rgba if (view[..., 3] > 0.5).any()]
    return float(np.mean(values)) if values else math.nan


def probe(root: Path, resolution: int, alphas: list[float], folds: int) -> dict:
    ids, feats = [], []
    for split in ("train", "val", "test"):
        if not read_split(root, split):
            continue
        part = pooled_splits([root], split, resolution)
        new = [i for i, aid in enumerate(part.ids) if aid not in ids]  # an asset listed twice counts once
        ids += [part.ids[i] for i in new]
        feats.append(part.views[new].mean(1).double().numpy())
    if not ids:
        raise UserError(f"{root} has no assets in its train, val or test split")
    material, position, span, tone = [], [], [], []
    for aid in ids:
        asset = load_asset(root / aid)
        phys = asset.physical
        if not phys.true_known:
            raise UserError(f"{root / aid} has no true physics: the probe needs synthetic assets")
        lo, hi = log10_E_range(phys.material)
        material.append(MATERIAL_NAMES.index(phys.material))
        position.append((math.log10(phys.E) - lo) / (hi - lo))
        span.append(hi - lo)
        tone.append(brightness(asset.load_rgba(list(range(0, len(asset), 4)))))
    x = np.concatenate(feats)
    material, position, span, tone = map(np.asarray, (material, position, span, tone))
    report = {
        "data": str(root),
        "assets": len(ids),
        "mid_range": round(float(np.median(np.abs(0.5 - position) * span)), 4),
        "ridge": [],
        "tone": {},
    }
    for alpha in alphas:
        pred = np.clip(ridge_cv(x, material, position, alpha, folds), 0.0, 1.0)
        report["ridge"].append(
            {
                "alpha": alpha,
                "median_abs_log10_E_error": round(float(np.median(np.abs(pred - position) * span)), 4),
                "correlation": round(float(np.corrcoef(pred, position)[0, 1]), 3),
            }
        )
    for m in np.unique(material):
        sel = material == m
        if sel.sum() >= 3:
            rho = float(spearmanr(tone[sel], position[sel])[0])  # nan where the tones tie (JSON: null)
            report["tone"][MATERIAL_NAMES[m]] = {
                "assets": int(sel.sum()),
                "spearman": round(rho, 3) if math.isfinite(rho) else None,
            }
    return report


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(
        prog="python -m physgm.bench stiffness-probe", description=__doc__.splitlines()[0]
    )
    p.add_argument("roots", nargs="+", type=Path, help="synthetic PhysAssets folders, each probed alone")
    p.add_argument("--resolution", type=int, default=128, help="input view size of the cached features")
    p.add_argument("--alphas", type=float, nargs="+", default=[10.0, 100.0, 1000.0])
    p.add_argument("--folds", type=int, default=5)
    a = p.parse_args(argv)
    if a.folds < 2 or min(a.alphas) <= 0:
        raise SystemExit(f"--folds must be at least 2 and every alpha > 0, got {a.folds} and {a.alphas}")
    try:
        report = {"data_sets": [probe(root, a.resolution, a.alphas, a.folds) for root in a.roots]}
    except UserError as e:
        raise SystemExit(f"stiffness-probe: {e}") from None
    print(json.dumps(report))
    return report


if __name__ == "__main__":
    main()
