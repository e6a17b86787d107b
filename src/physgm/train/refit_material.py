"""Refit the physics head's material classifier on the frozen encoder's pooled features.

    python -m physgm.train.refit_material CKPT --data ROOT [ROOT ...] --out OUT [--epochs 60] [--seed 0]
        [--procedural-expert]

Stage 1 trains the material classifier on global token 0, jointly with everything else. On the
synthetic assets a classifier of the frozen MobileNetV2's pyramid, pooled over space and views,
reads the material better than that token does (docs/model.md). This tool keeps every other
weight of CKPT, switches its head to ``material_input="features"`` and fits that classifier by
cross-entropy against the annotated material (stage 1's target) of the train split. Each epoch
draws one random set of 1 or 4 of every asset's cached views (the two input counts of training);
the epoch kept is the one with the best validation accuracy (true material where known, else the
annotation), scored on single views and on fixed sets of 4. Several roots pool their train splits
and their val splits (more procedural assets make a better classifier: docs/model.md). Only the
feature cache is read, so a fit takes minutes on the CPU. OUT keeps CKPT's hyper-parameters
(prior weight, calibration offsets) and is written atomically.

``--procedural-expert`` keeps the token classifier instead and fits the same classifier as the
head's second, procedural expert (``physics_head.procedural_expert``): the domain gate mixes it in
for scenes that look procedural, and the token classifier with the semantic prior keeps the real
objects. CKPT needs a domain gate (``python -m physgm.train.fit_gate``).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from types import MappingProxyType

import torch
from torch import Tensor

from physgm.data.datamodule import PhysAssetsDataModule
from physgm.data.format import load_asset, read_split
from physgm.errors import UserError
from physgm.model.checkpoint import PREFIX, Checkpoint, input_size, load_model, read_checkpoint
from physgm.model.physgm import PhysGM
from physgm.model.physics_head import PooledMaterialClassifier, pooled_features
from physgm.physics.materials import MATERIAL_NAMES
from physgm.train.export import slim


@dataclass
class RefitConfig:
    epochs: int = 60
    batch_size: int = 128
    lr: float = 1e-3
    weight_decay: float = 1e-2
    hidden: int = 256
    dropout: tuple[float, float] = (0.2, 0.3)  # on the standardised input, on the hidden layer
    p_single: float = 0.5  # share of 1-view draws; the rest average 4 views
    seed: int = 0
    procedural_expert: bool = False  # fit the head's procedural expert, keep its main classifier


@dataclass
class PooledSplit:
    """Every cached view of a split's assets, pooled one view at a time."""

    ids: list[str]
    views: Tensor  # [A, V, POOLED_DIM]
    annotated: Tensor  # [A] material index the annotator gave (stage 1's target)
    truth: Tensor  # [A] true material where known, else the annotation


def data_roots(data: Path | str | Sequence[Path | str]) -> list[Path]:
    """One data root or several, as a list of paths (the refits pool their splits)."""
    return [Path(data)] if isinstance(data, str | Path) else [Path(r) for r in data]


def pooled_splits(roots: list[Path], split: str, resolution: int) -> PooledSplit:
    """``pooled_split`` of every root that has assets in ``split``, concatenated."""
    parts = []
    for root in roots:
        if read_split(root, split):
            store = PhysAssetsDataModule(
                str(root), input_resolution=resolution, feature_cache="mobilenet_v2"
            ).feature_store((split,))
            parts.append(pooled_split(root, split, store))
    if not parts:
        raise UserError(f"no {split!r} assets to refit on in {', '.join(map(str, roots))}")
    if len({p.views.shape[1] for p in parts}) != 1:
        raise UserError(
            f"the feature caches of {roots} hold different numbers of views per asset; rebuild them"
        )
    return PooledSplit(
        sum((p.ids for p in parts), []),
        torch.cat([p.views for p in parts]),
        torch.cat([p.annotated for p in parts]),
        torch.cat([p.truth for p in parts]),
    )


def pooled_split(root: Path, split: str, store) -> PooledSplit:
    ids, views, annotated, truth = [], [], [], []
    for aid in read_split(root, split):
        phys = load_asset(root / aid).physical
        feats = store.load(aid)  # [V, ...] every cached view
        views.append(pooled_features(feats, batch=len(feats.s4)))  # one "scene" per view
        ids.append(aid)
        annotated.append(MATERIAL_NAMES.index(phys.annotation.material))
        truth.append(MATERIAL_NAMES.index(phys.material if phys.true_known else phys.annotation.material))
    if not ids:
        raise UserError(f"split {split!r} of {root} has no assets to refit on")
    counts = {len(v) for v in views}
    if len(counts) != 1 or min(counts) < 4:
        raise UserError(
            f"the feature cache of {root} holds {sorted(counts)} views per asset; the refit needs the "
            "same number, at least 4, for every asset: rebuild it with python -m physgm.data.feature_cache"
        )
    return PooledSplit(ids, torch.stack(views), torch.tensor(annotated), torch.tensor(truth))


def draw_scenes(views: Tensor, p_single: float, gen: torch.Generator) -> Tensor:  # [A, V, P] -> [A, P]
    """One random input set per asset: a single view with probability p_single, else 4 views averaged."""
    a, v, _ = views.shape
    order = torch.argsort(torch.rand(a, v, generator=gen), dim=1)[:, :4]  # 4 distinct views per asset
    four = torch.gather(views, 1, order[..., None].expand(-1, -1, views.shape[-1])).mean(1)
    one = views[torch.arange(a), order[:, 0]]
    single = (torch.rand(a, generator=gen) < p_single)[:, None]
    return torch.where(single, one, four)


def accuracy(
    classifier: PooledMaterialClassifier,
    views: Tensor,  # [A, V, POOLED_DIM]
    labels: Tensor,  # [A]
) -> dict[str, float]:
    """Accuracy on every single view, and on the views taken 4 at a time in cache order."""
    a, v, p = views.shape
    with torch.no_grad():
        one = classifier(views.reshape(a * v, p)).argmax(-1).reshape(a, v)
        sets = views[:, : v // 4 * 4].reshape(a, v // 4, 4, p).mean(2)
        four = classifier(sets.reshape(-1, p)).argmax(-1).reshape(a, -1)
    return {
        "views1": float((one == labels[:, None]).float().mean()),
        "views4": float((four == labels[:, None]).float().mean()),
    }


def fit(
    classifier: PooledMaterialClassifier, train: PooledSplit, val: PooledSplit, cfg: RefitConfig, log=print
) -> dict:
    """Train ``classifier`` in place; it ends holding the epoch with the best mean validation accuracy,
    whose row (epoch, loss, validation accuracies) it returns."""
    gen = torch.Generator().manual_seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    flat = train.views.flatten(0, 1)
    with torch.no_grad():
        classifier.shift.copy_(flat.mean(0))
        classifier.scale.copy_(flat.std(0) + 1e-3)  # a constant feature must not divide by ~0
    opt = torch.optim.AdamW(classifier.parameters(), cfg.lr, weight_decay=cfg.weight_decay)
    best, best_score, best_state = {}, -1.0, None
    for epoch in range(cfg.epochs):
        classifier.train()
        classifier.dropout = cfg.dropout
        x = draw_scenes(train.views, cfg.p_single, gen)
        perm = torch.randperm(len(x), generator=gen)
        total = 0.0
        for i in range(0, len(x), cfg.batch_size):
            b = perm[i : i + cfg.batch_size]
            loss = torch.nn.functional.cross_entropy(classifier(x[b]), train.annotated[b])
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(b)
        classifier.eval()
        classifier.dropout = (0.0, 0.0)
        scores = accuracy(classifier, val.views, val.truth)
        row = {"epoch": epoch + 1, "loss": total / len(x), **{f"val_{k}": v for k, v in scores.items()}}
        score = (row["val_views1"] + row["val_views4"]) / 2
        if score > best_score:
            best, best_score, best_state = row, score, copy.deepcopy(classifier.state_dict())
        if (epoch + 1) % 10 == 0:
            log(json.dumps(row))
    classifier.load_state_dict(best_state)
    return best


def refit(ckpt_path: Path, data: Path | Sequence[Path], out: Path, cfg: RefitConfig, log=print) -> dict:
    """Fit the features classifier for the model in ``ckpt_path`` on the data roots ``data`` and write the
    refitted model to ``out``."""
    roots = data_roots(data)
    old, ckpt = load_model(ckpt_path)
    if old.config.backbone.encoder.kind != "mobilenet_v2":
        raise UserError(
            f"{ckpt_path} has the {old.config.backbone.encoder.kind!r} encoder; the refit reads the "
            "frozen mobilenet_v2's cached features"
        )
    config = copy.deepcopy(old.config)
    head = config.physics_head
    if cfg.procedural_expert:
        if not head.domain_gate or head.material_input != "token":
            raise UserError(
                f"{ckpt_path}: a procedural expert sits beside a token material classifier and is mixed "
                f"in by the domain gate (this head: material_input={head.material_input!r}, "
                f"domain_gate={head.domain_gate}); fit the gate first: python -m physgm.train.fit_gate"
            )
        head.procedural_expert, refitted = True, "physics_head.procedural."
    else:
        head.material_input, refitted = "features", "physics_head.material."
    head.feature_hidden = cfg.hidden
    torch.manual_seed(cfg.seed)  # the new classifier's initial weights are the seed's, whatever ran before
    model = PhysGM(config, load_pretrained=False)
    kept = {k: v for k, v in old.state_dict().items() if not k.startswith(refitted)}
    missing, unexpected = model.load_state_dict(kept, strict=False)
    if unexpected or not all(k.startswith(refitted) for k in missing):
        raise RuntimeError(f"refit lost weights other than the material classifier: {missing} {unexpected}")
    classifier = model.physics_head.procedural if cfg.procedural_expert else model.physics_head.material
    start = time.perf_counter()
    resolution = input_size(old, ckpt.hparams)
    train, val = pooled_splits(roots, "train", resolution), pooled_splits(roots, "val", resolution)
    log(f"refit: {len(train.ids)} train / {len(val.ids)} val assets, {train.views.shape[1]} views each")
    best = fit(classifier, train, val, cfg, log)
    record = {
        "source": str(ckpt_path),
        "data": [str(r) for r in roots],
        "assets": {"train": len(train.ids), "val": len(val.ids)},
        "config": asdict(cfg),
        "best": best,
        "train_accuracy_annotated": accuracy(classifier, train.views, train.annotated),
        "seconds": round(time.perf_counter() - start, 1),
    }
    roots_arg = " ".join(map(str, roots))
    recipe = f"python -m physgm.train.refit_material {ckpt_path} --data {roots_arg} --epochs {cfg.epochs}"
    recipe += " --procedural-expert" if cfg.procedural_expert else ""
    save_refit(ckpt, ckpt_path, model, out, recipe, "refit_material", record)
    return record


def save_refit(
    ckpt: Checkpoint, ckpt_path: Path, model: PhysGM, out: Path, recipe: str, key: str, record: dict
) -> None:
    """Write ``model`` (refitted from ``ckpt``) as a slim checkpoint at ``out``, atomically, with the
    refit's ``record`` under ``physgm.<key>``."""
    exported = slim(ckpt, str(ckpt_path), recipe=recipe)
    exported["hyper_parameters"]["model"] = model.config.to_dict()
    exported["state_dict"] = {PREFIX + k: v.detach().clone() for k, v in model.state_dict().items()}
    exported["physgm"][key] = record
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    torch.save(exported, tmp)
    tmp.replace(out)  # never a half-written checkpoint under the final name
    read_checkpoint(out)  # the layout check every reader does


def refit_arguments(
    prog: str,
    description: str,
    epochs: int,
    seed: int,
    argv: list[str] | None,
    flags: Mapping[str, str] = MappingProxyType({}),
):
    """The command line every refit takes, ``CKPT --data ROOT [ROOT ...] --out OUT [--epochs N] [--seed S]``,
    plus the tool's own on/off ``flags`` (name -> help), checked."""
    p = argparse.ArgumentParser(prog=prog, description=description)
    for name, text in flags.items():
        p.add_argument(name, action="store_true", help=text)
    p.add_argument("ckpt", type=Path, help="stage-1 checkpoint")
    p.add_argument(
        "--data",
        type=Path,
        nargs="+",
        required=True,
        help="PhysAssets roots; their train and val splits pool",
    )
    p.add_argument("--out", type=Path, required=True, help="refitted checkpoint to write")
    p.add_argument("--epochs", type=int, default=epochs)
    p.add_argument("--seed", type=int, default=seed)
    a = p.parse_args(argv)
    if not a.ckpt.is_file():
        raise SystemExit(f"checkpoint {a.ckpt} not found")
    if a.out.resolve() == a.ckpt.resolve():
        raise SystemExit(f"--out {a.out} would overwrite the checkpoint being refitted; write elsewhere")
    return a


def run_refit(fn, a: argparse.Namespace, cfg) -> int:
    """Run ``fn(ckpt, data, out, cfg)``, progress on stderr, its JSON record on stdout."""
    try:
        record = fn(a.ckpt, a.data, a.out, cfg, log=_stderr)
    except UserError as err:
        raise SystemExit(str(err)) from None
    print(json.dumps(record))
    return 0


def main(argv: list[str] | None = None) -> int:
    doc = __doc__.split("\n")[0]
    flags = {"--procedural-expert": "fit the head's procedural expert beside its token classifier"}
    a = refit_arguments(
        "python -m physgm.train.refit_material", doc, RefitConfig.epochs, RefitConfig.seed, argv, flags
    )
    cfg = RefitConfig(epochs=a.epochs, seed=a.seed, procedural_expert=a.procedural_expert)
    return run_refit(refit, a, cfg)


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)  # stdout is for the JSON record


if __name__ == "__main__":
    sys.exit(main())
