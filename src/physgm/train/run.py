"""``run(cfg)``: what ``python train.py`` does, as a plain function tests can call."""

from __future__ import annotations

import importlib
import logging

from omegaconf import DictConfig

log = logging.getLogger(__name__)

# Stage name -> module with ``fit(cfg) -> dict`` that builds data, model and trainer and trains.
STAGES = {
    "pretrain": "physgm.train.pretrain",
    "dpo": "physgm.train.dpo",
}


def run(cfg: DictConfig) -> dict:
    """Train the stage named by ``cfg.stage.name`` and return its final metrics."""
    name = cfg.stage.name
    if name not in STAGES:
        raise ValueError(f"unknown stage {name!r}; choose one of {sorted(STAGES)} (e.g. stage=pretrain)")
    try:
        module = importlib.import_module(STAGES[name])
    except ModuleNotFoundError as err:
        if err.name != STAGES[name]:
            raise
        raise SystemExit(f"stage {name!r} is not part of this version of physgm yet ({STAGES[name]} is missing)") from None
    return module.fit(cfg)
