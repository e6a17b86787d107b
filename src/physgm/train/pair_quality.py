"""How good a DPO run's preference pairs are, judged against the scenes' true physics.

    python -m physgm.train.pair_quality RUN_DIR --data ROOT [--pairing anchor] [--json]

Reads every round of ``RUN_DIR/pairs/`` and, per material, counts:

- ``pairs``: scenes with a preference pair (the rest are ties or the policy's own draw winning);
- ``nearer``: pairs whose winner's log10 E is nearer the true E than the loser's;
- ``toward``: pairs that move the policy's E towards the truth. For a Gaussian policy the DPO
  gradient on the mean points from the loser to the winner wherever the mean is, so a pair helps
  when winner minus loser has the sign of the true E minus the policy's own draw (the scene's
  first candidate drawn from the policy, which stands in for its mean). Scenes without a policy
  draw are not counted here.

Pairs are taken as written, or with ``--pairing`` chosen again from the same candidates by that
rule (``physgm.train.pairs.PAIRINGS``), which compares rules without simulating. Only scenes
whose physical.json holds true physics count (synthetic assets, not annotated real ones). Prints
a table, or with ``--json`` one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from pathlib import Path

from physgm.data.format import load_asset
from physgm.train.pairs import PAIRINGS, SceneRecord, policy_draw

COUNTS = ("pairs", "nearer", "toward", "toward_counted", "no_pair")


def judge(records: list[SceneRecord], truth: dict[str, tuple[str, float]]) -> dict[str, dict[str, int]]:
    """Per material and "all": the counts of ``COUNTS`` over ``records`` whose scene is in ``truth``
    (scene id -> (material, true log10 E))."""
    out: dict[str, dict[str, int]] = defaultdict(lambda: dict.fromkeys(COUNTS, 0))
    for r in records:
        if r.scene not in truth:
            continue
        material, true_log10_E = truth[r.scene]
        rows = (out[material], out["all"])
        if not r.has_pair:
            for row in rows:
                row["no_pair"] += 1
            continue
        w, l = r.candidates[r.winner].log10_E, r.candidates[r.loser].log10_E
        k = policy_draw(r.candidates)
        draw = None if k is None else r.candidates[k].log10_E
        for row in rows:
            row["pairs"] += 1
            row["nearer"] += abs(w - true_log10_E) < abs(l - true_log10_E)
            if draw is not None:
                row["toward_counted"] += 1
                row["toward"] += (w - l) * (true_log10_E - draw) > 0
    return {m: out[m] for m in sorted(out, key=lambda m: (m == "all", m))}


def read_round(folder: Path, pairing: str | None = None, min_gap: float = 0.002) -> list[SceneRecord]:
    """The finished scene records of one ``round_*`` folder (not its summary or temporaries),
    paired again by ``pairing`` unless it is None."""
    records = []
    for f in sorted(folder.glob("*.json")):
        if f.name.startswith(("_", ".")):
            continue
        record = SceneRecord.from_json(json.loads(f.read_text()))
        if not record.complete:
            continue
        if pairing is not None:
            record.pair_again(min_gap, pairing)
        records.append(record)
    return records


def read_truth(root: Path, scenes: set[str]) -> dict[str, tuple[str, float]]:
    """Scene id -> (material, log10 E) for the scenes of ``root`` with true physics."""
    truth = {}
    for scene in sorted(scenes):
        physical = load_asset(root / scene).physical
        if physical.true_known:
            truth[scene] = (physical.material, math.log10(physical.E))
    return truth


def share(n: int, d: int) -> str:
    return f"{n}/{d} ({n / d:.2f})" if d else "-"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m physgm.train.pair_quality", description=__doc__.split("\n")[0]
    )
    p.add_argument("run", type=Path, help="a DPO run folder (holds pairs/round_*/)")
    p.add_argument("--data", type=Path, required=True, help="the data set root its scenes come from")
    p.add_argument(
        "--pairing", choices=PAIRINGS, help="choose each pair again by this rule (default: as written)"
    )
    p.add_argument("--min-gap", type=float, default=0.002, help="with --pairing: stage.rollout.min_gap")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    a = p.parse_args(argv)
    rounds = sorted((a.run / "pairs").glob("round_*"))
    if not rounds:
        p.error(f"no pairs/round_*/ folders under {a.run}; give the run folder of `train.py stage=dpo`")
    records = {r.name: read_round(r, a.pairing, a.min_gap) for r in rounds}
    truth = read_truth(a.data, {rec.scene for recs in records.values() for rec in recs})
    if not truth:
        p.error(f"no scene of {a.run} has true physics in {a.data}; is --data the run's data root?")
    result = {name: judge(recs, truth) for name, recs in records.items()}
    if a.json:
        print(json.dumps(result, indent=1))
        return 0
    print("| round | material | pairs | no pair | winner nearer the true E | pushes the policy towards it |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name, per_material in result.items():
        for m, c in per_material.items():
            print(
                f"| {name} | {m} | {c['pairs']} | {c['no_pair']} | {share(c['nearer'], c['pairs'])} | "
                f"{share(c['toward'], c['toward_counted'])} |"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
