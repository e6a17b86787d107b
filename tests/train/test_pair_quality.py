"""python -m physgm.train.pair_quality: pair counts against the scenes' true E, hand-computed."""

from __future__ import annotations

import json
import math

import pytest

from physgm.data.format import load_asset
from physgm.data.synth import SynthConfig, asset_id, generate
from physgm.train import pair_quality
from physgm.train.pairs import Candidate, PairCache, SceneRecord, select_pair

# Per scene: (offset of log10 E from the truth, distance, source) of its three candidates.
SCENES = [
    [(2.0, 0.5, "wide"), (0.1, 0.1, "wide"), (1.0, 0.3, "policy")],  # both rules: nearer, towards
    [(-2.0, 0.1, "wide"), (0.5, 0.9, "wide"), (1.0, 0.5, "policy")],  # winner farther, but towards
    [(0.5, 0.1, "wide"), (-2.0, 0.9, "wide"), (1.0, 0.5, "policy")],  # best vs worst pushes away
    [(3.0, 0.9, "wide"), (-3.0, 0.8, "wide"), (0.2, 0.1, "policy")],  # the policy's draw wins
]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("pq") / "data"
    generate(
        SynthConfig(count=len(SCENES), seed=3, resolution=16, gaussians=50), root, workers=1, progress=False
    )
    run_dir = root.parent / "run"
    cache = PairCache(run_dir / "pairs")
    for i, spec in enumerate(SCENES):
        truth = math.log10(load_asset(root / asset_id(i)).physical.E)
        cands = [Candidate(0, "x", truth + off, 0.3, d, source=src) for off, d, src in spec]
        w, l, note = select_pair(cands, 0.002)  # written by the paper's rule
        cache.write(SceneRecord(asset_id(i), i, 0, "s", "p", cands, w, l, 0, note))
    (run_dir / "pairs" / "round_0000" / "_summary.json").write_text("{}")
    return run_dir, root


def counts(capsys, argv) -> dict:
    assert pair_quality.main(argv + ["--json"]) == 0
    return json.loads(capsys.readouterr().out)["round_0000"]


def test_counts_as_written_and_with_anchor_pairs(run, capsys):
    run_dir, root = run
    written = counts(capsys, [str(run_dir), "--data", str(root)])
    assert written["all"] == {"pairs": 4, "nearer": 3, "toward": 3, "toward_counted": 4, "no_pair": 0}
    per_material = [c for m, c in written.items() if m != "all"]
    assert sum(c["pairs"] for c in per_material) == 4
    anchored = counts(capsys, [str(run_dir), "--data", str(root), "--pairing", "anchor"])
    assert anchored["all"] == {"pairs": 3, "nearer": 2, "toward": 3, "toward_counted": 3, "no_pair": 1}


def test_a_folder_without_rounds_is_a_clear_error(run, tmp_path, capsys):
    with pytest.raises(SystemExit):
        pair_quality.main([str(tmp_path), "--data", str(run[1])])
    assert "no pairs/round_*/ folders" in capsys.readouterr().err
