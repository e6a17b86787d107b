"""The stiffness probe: cross-validated ridge from pooled features, and its report on a data set."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from physgm.bench import stiffness_probe
from physgm.physics.materials import log10_E_range


def _assets(n: int = 240, dim: int = 16, signal: bool = True, seed: int = 0):
    rng = np.random.default_rng(seed)
    groups = rng.integers(3, size=n)
    position = rng.random(n)
    x = rng.normal(size=(n, dim))
    if signal:  # one feature carries the position, offset per group as a material's look would be
        x[:, 3] = position + 2.0 * groups + 0.05 * rng.normal(size=n)
    return x, groups, position


def test_the_probe_reads_a_position_a_feature_carries_and_not_one_it_does_not():
    x, groups, position = _assets()
    pred = stiffness_probe.ridge_cv(x, groups, position, alpha=1.0)
    assert np.median(np.abs(pred - position)) < 0.08 and np.corrcoef(pred, position)[0, 1] > 0.95
    x, groups, position = _assets(signal=False)
    pred = stiffness_probe.ridge_cv(x, groups, position, alpha=1.0)
    # Noise features: no better than the middle of the range (median error 0.25 for a uniform position).
    assert np.median(np.abs(pred - position)) > 0.2 and abs(np.corrcoef(pred, position)[0, 1]) < 0.3


def test_the_report_of_a_data_set_scores_the_mid_range_guess_from_its_labels(tiny_dataset, tmp_path, capsys):
    root = tmp_path / "data"
    shutil.copytree(tiny_dataset, root)
    splits = root / "splits"
    (splits / "val.txt").write_text((splits / "train.txt").read_text())  # assets listed twice count once
    report = stiffness_probe.main([str(root), "--resolution", "64", "--folds", "2", "--alphas", "10"])
    assert json.loads(capsys.readouterr().out) == report
    (probe,) = report["data_sets"]
    assets = sorted(p.parent for p in root.glob("syn_*/physical.json"))
    assert probe["assets"] == len(assets) == 10
    errors = []
    for a in assets:
        phys = json.loads((a / "physical.json").read_text())
        lo, hi = log10_E_range(phys["material"])
        errors.append(abs(math.log10(phys["E"]) - (lo + hi) / 2))
    assert probe["mid_range"] == pytest.approx(float(np.median(errors)), abs=1e-4)
    (ridge,) = probe["ridge"]
    assert ridge["alpha"] == 10.0 and 0 <= ridge["median_abs_log10_E_error"] <= max(errors)


def test_too_few_assets_for_the_folds_is_a_clear_error(tiny_dataset):
    with pytest.raises(SystemExit, match="at least 24 assets for 12 folds"):
        stiffness_probe.main([str(tiny_dataset), "--resolution", "64", "--folds", "12"])
