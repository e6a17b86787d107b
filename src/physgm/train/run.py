"""``run(cfg)``: what ``python train.py`` does, as a plain function tests can call."""

from __future__ import annotations

import importlib
import logging
import sys
from typing import Any

import lightning as L
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from physgm.errors import UserError

log = logging.getLogger(__name__)

# Stage name -> module with ``fit(cfg) -> dict`` that builds data, model and trainer and trains.
STAGES = {
    "pretrain": "physgm.train.pretrain",
    "dpo": "physgm.train.dpo",
}


def main(cfg: DictConfig) -> None:
    """Hydra entry (train.py, physgm-train): a user error prints ``error: ...`` and exits with code 2."""
    try:
        run(cfg)
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None


def run(cfg: DictConfig) -> dict:
    """Train the stage named by ``cfg.stage.name`` and return its final metrics."""
    name = cfg.stage.name
    if name not in STAGES:
        raise UserError(f"unknown stage {name!r}; choose one of {sorted(STAGES)} (e.g. stage=pretrain)")
    threads = int(cfg.get("torch_threads") or 0)
    if threads < 0:
        raise UserError(f"torch_threads must be >= 0 (0: torch's default), got {threads}")
    if threads:
        torch.set_num_threads(threads)
    return importlib.import_module(STAGES[name]).fit(cfg)


def plain(node: Any) -> Any:
    """A config node as plain Python containers, resolved, without Hydra's ``_target_`` keys."""
    if node is None:
        return None
    out = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
    if isinstance(out, dict):
        out = {k: plain(v) for k, v in out.items() if k != "_target_"}
    return out


def build_trainer(cfg: DictConfig, extra_callbacks: list | None = None) -> L.Trainer:
    """The Lightning trainer with the configured loggers and callbacks."""
    callbacks = [instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c is not None]
    loggers = [instantiate(c) for c in (cfg.get("logger") or {}).values() if c is not None]
    return instantiate(
        cfg.trainer, callbacks=callbacks + list(extra_callbacks or []), logger=loggers or False
    )


def ensure_data(cfg: DictConfig, root: str | None = None, split: str | None = None) -> None:
    """Make sure the data set ``root`` (default ``cfg.data.root``) has the split list ``split``.

    A missing set is generated when it is the folder ``cfg.synth.out`` names (``cfg.synth`` holds
    ``physgm.data.synth.SynthConfig`` fields plus ``out`` and ``workers``); a partly generated one
    is resumed. Any other missing set stops with one sentence saying what to add.
    """
    from pathlib import Path

    root = Path(root or cfg.data.root)
    split = split or cfg.data.get("train_split", "train")
    if (root / "splits" / f"{split}.txt").is_file() or cfg.data.get("backend", "folder") != "folder":
        return
    synth = cfg.get("synth")
    if synth is None or Path(str(synth.out)).absolute() != root.absolute():
        raise SystemExit(
            f"error: no data set at {root} ({root / 'splits' / f'{split}.txt'} is missing); make it with "
            f"`python -m physgm.data.synth --out {root} --count 1000 --seed 0 --workers 2`, or add "
            f"experiment=tiny_cpu "
            "(stage 1) or experiment=tiny_cpu_dpo (stage 2) to train on a small set made on first use"
        )
    from physgm.data.synth import SynthConfig, generate

    options = plain(synth)
    options.pop("out")
    workers = int(options.pop("workers", 1))
    log.info(
        "generating the synthetic data set %s (%s assets); later runs reuse it", root, options.get("count")
    )
    summary = generate(SynthConfig(**options), root, workers=workers, progress=True)
    if summary["failed"]:
        raise RuntimeError(f"data generation failed for {summary['failed']} assets: {summary['failures']}")
