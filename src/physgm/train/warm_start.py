"""Stage 1 started from another checkpoint's weights: ``python train.py stage.init_ckpt=PATH``.

The run's own model config decides the architecture; the checkpoint only supplies weights. That
serves fine-tuning (the same model trained further with another loss, data or schedule) and a
changed head option, for example ``model.gaussian_head.depth_prior=hull``, whose output conv
takes two more input channels than the ``range`` model it starts from.

Each weight of the new model is one of:

- **copied**: the checkpoint has it with the same shape;
- **widened**: the checkpoint has it with fewer input channels (dimension 1) and the same shape
  otherwise. The checkpoint's channels are copied and the new ones set to zero, so the layer
  computes what it did as long as the new inputs come after the old ones (the hull guide is
  concatenated last);
- **branched**: a weight of the backbone's geometry blocks (``model.backbone.geometry_blocks``)
  that the checkpoint does not have starts as a copy of the shared block it duplicates, so the
  new model computes what the checkpoint's did (a checkpoint with fewer copies keeps them as the
  last ones, and the blocks before them are copied); so does the last output conv of a Gaussian layer
  the checkpoint does not have (``model.gaussian_head.layers``), as a copy of the first layer's,
  which its opacity shift makes faint at the start;
- **new**: the checkpoint does not have it; it keeps its fresh initialisation.

Anything else (a shape that differs in another way, or checkpoint weights the new model does not
have) means the configs describe different models, and is an error that names the weights.
``ckpt_path`` (resuming a run) is applied after this and replaces everything, optimiser included.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn

from physgm.errors import UserError
from physgm.model.checkpoint import read_checkpoint


@dataclass
class WarmStart:
    """Which weights came from where."""

    path: Path
    copied: list[str] = field(default_factory=list)
    widened: list[str] = field(default_factory=list)
    branched: list[str] = field(default_factory=list)
    new: list[str] = field(default_factory=list)

    def summary(self) -> str:
        parts = [f"{len(self.copied)} weights copied"]
        if self.widened:
            parts.append(f"{len(self.widened)} widened with zero input channels ({', '.join(self.widened)})")
        if self.branched:
            parts.append(
                f"{len(self.branched)} weights of geometry blocks or Gaussian layers copied from the ones "
                "they duplicate"
            )
        if self.new:
            parts.append(f"{len(self.new)} new ({', '.join(self.new)})")
        return f"stage 1 starts from {self.path}: " + "; ".join(parts)


def _widens(old: torch.Size, new: torch.Size) -> bool:
    """True when ``new`` is ``old`` with more entries along dimension 1 (input channels) only."""
    return len(old) == len(new) >= 2 and old[0] == new[0] and old[2:] == new[2:] and old[1] < new[1]


def _copies_renumbered(state: dict, hparams: dict, count: int) -> dict:
    """``state`` with a checkpoint's geometry-block copies renumbered for a model with ``count``:
    the checkpoint's ``had`` copies are of the last ``had`` blocks, so its copy j is the new model's
    copy j + count - had. Unchanged when the counts agree or the checkpoint has no copies."""
    had = int(hparams.get("model", {}).get("backbone", {}).get("geometry_blocks", 0) or 0)
    if not had or count <= had:
        return state
    prefix = "backbone.geometry_blocks."

    def renamed(name: str) -> str:
        if not name.startswith(prefix):
            return name
        index, rest = name[len(prefix) :].split(".", 1)
        return f"{prefix}{int(index) + count - had}.{rest}"

    return {renamed(name): value for name, value in state.items()}


def warm_start(model: nn.Module, path: Path | str) -> WarmStart:
    """Load the weights of the checkpoint at ``path`` into ``model`` (a ``PhysGM``), as above.

    Raises:
        UserError: the checkpoint does not read (``read_checkpoint``'s messages), or its weights
            do not fit this model other than by the widening above.
    """
    ckpt = read_checkpoint(path)
    state = _copies_renumbered(ckpt.state, ckpt.hparams, model.config.backbone.geometry_blocks)
    report = WarmStart(ckpt.path)
    own = model.state_dict()
    unknown = sorted(set(state) - set(own))
    mismatched = [
        f"{k} {tuple(state[k].shape)} -> {tuple(v.shape)}"
        for k, v in own.items()
        if k in state and state[k].shape != v.shape and not _widens(state[k].shape, v.shape)
    ]
    if unknown or mismatched:
        problems = []
        if unknown:
            problems.append(f"weights this model does not have: {', '.join(unknown[:4])}")
        if mismatched:
            problems.append(f"weights of another shape: {', '.join(mismatched[:4])}")
        raise UserError(
            f"stage.init_ckpt={path} is a different model from this run's model config "
            f"({'; '.join(problems)}). "
            "Start from a checkpoint of the same architecture (the same model and backbone settings), or "
            "drop stage.init_ckpt to train from scratch"
        )
    sources = {f"backbone.{k}": f"backbone.{v}" for k, v in model.backbone.geometry_block_sources().items()}
    sources |= {
        f"gaussian_head.dpt.{k}": f"gaussian_head.dpt.{v}"
        for k, v in model.gaussian_head.dpt.layer_sources().items()
    }
    merged = {}
    for name, value in own.items():
        old = state.get(name)
        source = sources.get(name)
        if old is None and source in state:
            report.branched.append(name)
            merged[name] = state[source].to(value.dtype)
        elif old is None:
            report.new.append(name)
            merged[name] = value
        elif old.shape == value.shape:
            report.copied.append(name)
            merged[name] = old.to(value.dtype)
        else:
            report.widened.append(name)
            grown = torch.zeros_like(value)
            grown[:, : old.shape[1]] = old.to(value.dtype)
            merged[name] = grown
    model.load_state_dict(merged)
    return report
