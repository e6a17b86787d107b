"""Fit the domain gate of a stage-1 model: procedural training assets against real objects.

    python -m physgm.train.fit_gate CKPT --data ROOT [ROOT ...] --real GATE_ROOT --out OUT
        [--held-out REAL_ROOT] [--l2 0.1]

The gate (``physgm.model.domain_gate``) is a logistic regression on one view's pooled frozen-encoder
features: label 0 for every cached view of the ROOTs' ``train`` splits (the synthetic assets the
heads learned from), label 1 for every view of GATE_ROOT's ``train`` split (``python -m
physgm.data.real_objects --set gate``: real objects kept apart from the evaluation set). The two
classes weigh the same however many views each has, and an L2 penalty on the standardised weights
(``--l2``) keeps the fit from memorising a few dozen objects. Every other weight of CKPT is kept;
OUT has ``physics_head.domain_gate`` on, and is written atomically.

The record on stdout says how well the gate separates what it never saw: the area under the ROC
curve over single views and the 10th / 50th / 90th percentiles of P(real) per 1-view and 4-view
scene, on the ROOTs' ``val`` splits and on ``--held-out``'s ``val`` and ``test`` splits (the real
evaluation set, only scored here).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch import Tensor

from physgm.data.format import read_split
from physgm.errors import UserError
from physgm.model.checkpoint import input_size, load_model
from physgm.model.domain_gate import DomainGate
from physgm.model.physgm import PhysGM
from physgm.train.refit_material import data_roots, pooled_splits, save_refit


@dataclass
class GateConfig:
    l2: float = 0.1  # penalty on the squared standardised weights, added to the class-balanced mean loss
    max_iter: int = 500  # L-BFGS iterations (the loss is convex: this is a tolerance, not a schedule)


def split_views(roots: list[Path], split: str, resolution: int) -> Tensor:  # [A, V, POOLED_DIM]
    """Every cached view of the roots' ``split`` assets, pooled one view at a time (empty if none)."""
    if not any(read_split(r, split) for r in roots):
        return torch.zeros(0, 0, 0)
    return pooled_splits(roots, split, resolution).views


def fit_regression(
    synthetic: Tensor,  # [S, POOLED_DIM] single views, label 0
    real: Tensor,  # [R, POOLED_DIM] single views, label 1
    cfg: GateConfig,
) -> tuple[Tensor, Tensor, Tensor, float]:  # shift, scale, weight [POOLED_DIM]; bias
    """Class-balanced, L2-penalised logistic regression on standardised features (deterministic)."""
    x = torch.cat([synthetic, real]).double()
    y = torch.cat([torch.zeros(len(synthetic)), torch.ones(len(real))]).double()
    sample_weight = torch.where(y > 0, 0.5 / len(real), 0.5 / len(synthetic))  # each class sums to 1/2
    shift, scale = x.mean(0), x.std(0) + 1e-3  # a constant feature must not divide by ~0
    xs = (x - shift) / scale
    w = torch.zeros(x.shape[1], dtype=torch.float64, requires_grad=True)
    b = torch.zeros((), dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([w, b], max_iter=cfg.max_iter, line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        opt.zero_grad()
        loss = torch.nn.functional.binary_cross_entropy_with_logits(xs @ w + b, y, reduction="none")
        loss = (loss * sample_weight).sum() + cfg.l2 * (w * w).sum()
        loss.backward()
        return loss

    opt.step(closure)
    return shift.float(), scale.float(), w.detach().float(), float(b.detach())


def roc_auc(negative: Tensor, positive: Tensor) -> float:
    """P(a positive scores above a negative), ties counted half: the area under the ROC curve."""
    above = (positive[:, None] > negative[None, :]).double().mean()
    ties = (positive[:, None] == negative[None, :]).double().mean()
    return float(above + 0.5 * ties)


def scene_probabilities(gate: DomainGate, views: Tensor) -> dict[str, Tensor]:  # [A, V, P] -> [A * k]
    """P(real) of every single view, and of the views taken 4 at a time in cache order."""
    a, v, p = views.shape
    with torch.no_grad():
        logits = gate.view_logits(views)  # [A, V]
        four = logits[:, : v // 4 * 4].reshape(a, -1, 4).mean(-1)
    return {"views1": torch.sigmoid(logits).flatten(), "views4": torch.sigmoid(four).flatten()}


def summary(gate: DomainGate, views: Tensor) -> dict:
    levels = {"p10": 0.1, "p50": 0.5, "p90": 0.9}
    return {
        n: {k: round(float(p.quantile(q)), 3) for k, q in levels.items()}
        for n, p in scene_probabilities(gate, views).items()
    }


def fit_gate(
    ckpt_path: Path,
    data: Path | Sequence[Path],
    real_root: Path,
    out: Path,
    cfg: GateConfig,
    held_out: Path | None = None,
    log=print,
) -> dict:
    """Fit the gate for the model in ``ckpt_path``, write the gated model to ``out``, return the record."""
    old, ckpt = load_model(ckpt_path)
    if old.config.backbone.encoder.kind != "mobilenet_v2":
        raise UserError(
            f"{ckpt_path} has the {old.config.backbone.encoder.kind!r} encoder; the gate reads the "
            "frozen mobilenet_v2's cached features"
        )
    roots = data_roots(data)
    resolution = input_size(old, ckpt.hparams)
    start = time.perf_counter()
    synthetic, real = split_views(roots, "train", resolution), split_views([real_root], "train", resolution)
    if not len(synthetic) or not len(real):
        raise UserError(
            f"the gate needs synthetic training assets ({', '.join(map(str, roots))}: {len(synthetic)}) "
            "and real ones "
            f"({real_root}: {len(real)}; python -m physgm.data.real_objects --set gate --out {real_root})"
        )
    log(f"fit_gate: {len(synthetic)} synthetic / {len(real)} real training assets")
    shift, scale, weight, bias = fit_regression(synthetic.flatten(0, 1), real.flatten(0, 1), cfg)
    config = copy.deepcopy(old.config)
    config.physics_head.domain_gate = True
    model = PhysGM(config, load_pretrained=False)
    missing, unexpected = model.load_state_dict(old.state_dict(), strict=False)
    if unexpected or not all(k.startswith("domain_gate.") for k in missing):
        raise RuntimeError(f"fit_gate lost weights other than the gate's: {missing} {unexpected}")
    model.domain_gate.set_fit(shift, scale, weight, bias)
    gate = model.domain_gate
    record = {
        "source": str(ckpt_path),
        "data": [str(r) for r in roots],
        "real": str(real_root),
        "config": asdict(cfg),
        "train": {"synthetic": summary(gate, synthetic), "real": summary(gate, real)},
    }
    scored = {"synthetic_val": split_views(roots, "val", resolution)}
    if held_out is not None:
        scored |= {name: split_views([held_out], name[5:], resolution) for name in ("real_val", "real_test")}
    for name, views in scored.items():
        if len(views):
            record[name] = summary(gate, views)
    negative = scored["synthetic_val"]
    for name in ("real_val", "real_test"):
        if name in scored and len(scored[name]) and len(negative):
            with torch.no_grad():
                record[name]["view_auc"] = round(
                    roc_auc(gate.view_logits(negative).flatten(), gate.view_logits(scored[name]).flatten()), 4
                )
    record["seconds"] = round(time.perf_counter() - start, 1)
    recipe = (
        f"python -m physgm.train.fit_gate {ckpt_path} --data {' '.join(map(str, roots))} --real {real_root} "
        f"--l2 {cfg.l2}"
    )
    save_refit(ckpt, ckpt_path, model, out, recipe, "fit_gate", record)
    return record


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m physgm.train.fit_gate", description=__doc__.split("\n")[0])
    p.add_argument("ckpt", type=Path, help="stage-1 checkpoint with the mobilenet_v2 encoder")
    p.add_argument(
        "--data", type=Path, nargs="+", required=True, help="synthetic PhysAssets roots (train splits)"
    )
    p.add_argument("--real", type=Path, required=True, help="real objects for the gate (its train split)")
    p.add_argument("--out", type=Path, required=True, help="gated checkpoint to write")
    p.add_argument("--held-out", type=Path, default=None, help="real evaluation set, scored only")
    p.add_argument("--l2", type=float, default=GateConfig.l2)
    a = p.parse_args(argv)
    if not a.ckpt.is_file():
        raise SystemExit(f"checkpoint {a.ckpt} not found")
    if a.out.resolve() == a.ckpt.resolve():
        raise SystemExit(f"--out {a.out} would overwrite the checkpoint being gated; write elsewhere")
    try:
        record = fit_gate(a.ckpt, a.data, a.real, a.out, GateConfig(l2=a.l2), a.held_out, log=_stderr)
    except UserError as err:
        raise SystemExit(str(err)) from None
    print(json.dumps(record))
    return 0


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)  # stdout is for the JSON record


if __name__ == "__main__":
    sys.exit(main())
