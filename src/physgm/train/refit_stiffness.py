"""Refit the physics head's E regression relative to the material's range, on a frozen stage-1 model.

    python -m physgm.train.refit_stiffness CKPT --data ROOT [ROOT ...] --out OUT [--epochs 300] [--seed 0]

Stage 1 regresses one Gaussian on log10 E over 1 kPa .. 500 GPa for every material. Unsure between
a soft and a stiff material, it puts its mean between them, often outside both materials' ranges:
on held-out synthetic scenes its posterior mean is further from the true E than the centre of the
predicted material's range (docs/model.md). This tool keeps every other weight of CKPT, switches the
head to ``E_frame="material"`` (z_E = -1, 1 are the ends of the material's own range) and fits a fresh
E regression (the same MLP on global token 1) by the Gaussian NLL of the true E, read in the true
material's frame, on the train split. The global tokens are computed once by the frozen model, for
the fixed 4-view and 1-view input sets of each asset. The epoch kept is the one with the lowest
validation median abs(log10 E error) of the posterior mean, whose frame is the predicted material's
(at the semantic prior weight 0: the data is procedural), over 1 and 4 views. The log-variance
calibration offset of E is reset to 0: run ``python -m physgm.train.evaluate`` on a validation split
and export with ``--logvar-offsets`` to calibrate the new head. Several roots pool their train
splits and their val splits. OUT is written atomically.
"""

from __future__ import annotations

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
from physgm.model.physgm import PhysGM
from physgm.model.physics_head import PhysicsHead, _mean_logvar_mlp
from physgm.model.posterior import denormalise_log10_E, material_E_ranges
from physgm.train.evaluate import view_datamodule
from physgm.train.refit_material import data_roots, refit_arguments, run_refit, save_refit


@dataclass
class StiffnessRefitConfig:
    epochs: int = 300
    batch_size: int = 64
    lr: float = 1e-3
    weight_decay: float = 1e-2
    eval_every: int = 10  # epochs between validation scores (the best scored epoch is kept)
    seed: int = 0


@dataclass
class TokenSplit:
    """What the E regression reads and fits, per input set (each asset once with 4 views, once with 1)."""

    tokens: Tensor  # [N, D] global token 1
    material_logits: Tensor  # [N, M] the model's at prior weight 0 (its procedural expert's, if gated)
    material: Tensor  # [N] true material, else the annotation
    log10_E: Tensor  # [N] true log10 E, else the annotation
    views: Tensor  # [N] 1 or 4


def token_split(model: PhysGM, root: Path, split: str, resolution: int) -> TokenSplit:
    """Run the frozen model once per asset and input-view count; keep what the physics head reads."""
    seen: list[Tensor] = []
    hook = model.physics_head.register_forward_hook(lambda mod, args, out: seen.append(args[0][:, 1]))
    parts: list[tuple[Tensor, ...]] = []
    try:
        for views in (4, 1):
            dm = view_datamodule(model, str(root), split, views, resolution, num_targets=4, batch_size=8)
            for batch in dm.test_dataloader():
                seen.clear()
                with torch.no_grad():
                    out = model(batch.images, batch.masks, batch.c2w, batch.Ks, batch.features)
                tokens, logits = seen[-1], out.physics.material_logits
                known = batch.true_known
                material = torch.where(known, batch.true_material, batch.material)
                log10_E = torch.where(known, batch.true_log10_E, batch.log10_E)
                parts.append((tokens, logits, material, log10_E, torch.full_like(material, views)))
    finally:
        hook.remove()
    if not parts:
        raise UserError(f"split {split!r} of {root} has no assets to refit on")
    return TokenSplit(*(torch.cat(x) for x in zip(*parts, strict=True)))


def token_splits(model: PhysGM, roots: list[Path], split: str, resolution: int) -> TokenSplit:
    """``token_split`` of every root that has assets in ``split``, concatenated."""
    parts = [token_split(model, r, split, resolution) for r in roots if read_split(r, split)]
    if not parts:
        raise UserError(f"no {split!r} assets to refit on in {', '.join(map(str, roots))}")
    return TokenSplit(*(torch.cat(x) for x in zip(*(vars(p).values() for p in parts), strict=True)))


def posterior_mean_errors(head: PhysicsHead, data: TokenSplit, centre: bool = False) -> Tensor:  # [N]
    """abs(log10 E error) of the posterior mean, in the head's frame (E_frame "material": the predicted
    material's). ``centre``: of z_E = 0 in the material frame instead, the centre of the predicted
    material's range (the baseline a head that reads no stiffness cue would reach)."""
    with torch.no_grad():
        mean = torch.zeros(len(data.tokens)) if centre else head.young(data.tokens)[:, 0]
    if head.cfg.E_frame == "global" and not centre:
        return (denormalise_log10_E(mean) - data.log10_E).abs()
    ranges = material_E_ranges().to(mean)
    lo, hi = ranges[data.material_logits.argmax(-1)].unbind(-1)
    return (lo + (mean + 1.0) * 0.5 * (hi - lo) - data.log10_E).abs()


def validation_score(head: PhysicsHead, data: TokenSplit, centre: bool = False) -> dict[str, float]:
    err = posterior_mean_errors(head, data, centre)
    out = {f"views{v}": float(err[data.views == v].median()) for v in (1, 4) if (data.views == v).any()}
    out["mean"] = sum(out.values()) / len(out)
    return out


def fit(head: PhysicsHead, train: TokenSplit, val: TokenSplit, cfg: StiffnessRefitConfig, log=print) -> dict:
    """Train ``head.young`` in place by the Gaussian NLL in the true material's frame; it ends holding
    the scored epoch with the lowest mean validation error, whose row it returns."""
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    ranges = material_E_ranges().to(train.tokens)
    lo, hi = ranges[train.material].unbind(-1)
    target = 2.0 * (train.log10_E - lo) / (hi - lo) - 1.0
    opt = torch.optim.AdamW(head.young.parameters(), cfg.lr, weight_decay=cfg.weight_decay)
    best, best_state = {"val_mean": float("inf")}, copy.deepcopy(head.young.state_dict())
    for epoch in range(cfg.epochs):
        head.young.train()
        perm = torch.randperm(len(target), generator=gen)
        total = 0.0
        for i in range(0, len(perm), cfg.batch_size):
            b = perm[i : i + cfg.batch_size]
            mean, raw = head.young(train.tokens[b]).unbind(-1)
            logvar = head._logvar(raw)
            loss = 0.5 * (logvar + (target[b] - mean) ** 2 * torch.exp(-logvar)).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(b)
        if (epoch + 1) % cfg.eval_every:
            continue
        head.young.eval()
        scores = validation_score(head, val)
        row = {"epoch": epoch + 1, "nll": total / len(perm), **{f"val_{k}": v for k, v in scores.items()}}
        log(json.dumps(row))
        if row["val_mean"] < best["val_mean"]:
            best, best_state = row, copy.deepcopy(head.young.state_dict())
    head.young.load_state_dict(best_state)
    head.young.eval()
    return best


def refit(
    ckpt_path: Path, data: Path | Sequence[Path], out: Path, cfg: StiffnessRefitConfig, log=print
) -> dict:
    """Fit a material-frame E regression for the model in ``ckpt_path`` on the data roots ``data`` and
    write the model to ``out``."""
    roots = data_roots(data)
    model, ckpt = load_model(ckpt_path)
    model.eval()
    head_cfg = model.config.physics_head
    if head_cfg.num_materials != len(material_E_ranges()):
        raise UserError(f"{ckpt_path} has {head_cfg.num_materials} materials; the material table has a "
                        f"different number, so its E ranges cannot frame this head")  # fmt: skip
    head_cfg.semantic_prior_weight, prior = 0.0, head_cfg.semantic_prior_weight  # procedural data
    start = time.perf_counter()
    res = input_size(model, ckpt.hparams)
    train, val = token_splits(model, roots, "train", res), token_splits(model, roots, "val", res)
    log(f"refit_stiffness: {len(train.tokens)} train / {len(val.tokens)} val input sets")
    before = validation_score(model.physics_head, val)  # CKPT's own head
    head_cfg.E_frame, head_cfg.E_logvar_offset = "material", 0.0
    torch.manual_seed(cfg.seed)
    dim = model.physics_head.young[0].normalized_shape[0]  # the global tokens' width
    model.physics_head.young = _mean_logvar_mlp(dim, head_cfg.hidden)
    best = fit(model.physics_head, train, val, cfg, log)
    head_cfg.semantic_prior_weight = prior
    record = {
        "source": str(ckpt_path),
        "data": [str(r) for r in roots],
        "config": asdict(cfg),
        "val_before": before,
        "val_centre_of_predicted_material": validation_score(model.physics_head, val, centre=True),
        "best": best,
        "seconds": round(time.perf_counter() - start, 1),
    }
    recipe = (
        f"python -m physgm.train.refit_stiffness {ckpt_path} --data {' '.join(map(str, roots))} "
        f"--epochs {cfg.epochs}"
    )
    save_refit(ckpt, ckpt_path, model, out, recipe, "refit_stiffness", record)
    return record


def main(argv: list[str] | None = None) -> int:
    doc = __doc__.split("\n")[0]
    cfg = StiffnessRefitConfig
    a = refit_arguments("python -m physgm.train.refit_stiffness", doc, cfg.epochs, cfg.seed, argv)
    if a.epochs < cfg.eval_every:
        raise SystemExit(f"--epochs must be at least {cfg.eval_every} (one scored epoch)")
    return run_refit(refit, a, StiffnessRefitConfig(epochs=a.epochs, seed=a.seed))


if __name__ == "__main__":
    sys.exit(main())
