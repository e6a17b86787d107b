"""Slim a training checkpoint down to what inference needs, e.g. the shipped ``checkpoints/physgm_tiny.ckpt``.

    python -m physgm.train.export outputs/<run>/checkpoints/last.ckpt checkpoints/physgm_tiny.ckpt \
        [--recipe "python train.py experiment=tiny_cpu ..."] [--metrics test_metrics.json] \
        [--prior-weight W] [--logvar-offsets E NU] [--material-temperature T]

Keeps the model weights, the hyper-parameters that rebuild the model (and the renderer and input
settings evaluation reads), the step count and a ``physgm`` record of where the file came from;
drops optimiser, scheduler, loop and callback states (for AdamW two thirds of the file). The
result loads with ``physgm.model.checkpoint.load_model`` and ``LitPretrain.load_from_checkpoint``.
"""

from __future__ import annotations

import argparse
import copy
import datetime
import json
import subprocess
import sys
from pathlib import Path

import torch

import physgm
from physgm.errors import UserError
from physgm.model.checkpoint import PREFIX, Checkpoint, read_checkpoint
from physgm.model.config import PhysGMConfig

KEEP_HPARAMS = ("model", "renderer", "inputs", "format_version")


def git_revision(cwd: Path) -> str | None:
    """The commit of the working tree the export runs in (None outside git)."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def slim(
    ckpt: Checkpoint,
    source: str,
    recipe: str | None = None,
    metrics: dict | None = None,
    prior_weight: float | None = None,
    logvar_offsets: tuple[float, float] | None = None,
    prior_temperature: float | None = None,
    material_temperature: float | None = None,
) -> dict:
    """The inference part of a Lightning checkpoint of ``LitPretrain`` or ``LitDPO``.

    ``prior_weight`` and ``prior_temperature`` set the semantic prior's weight w and classifier
    temperature T in the exported model (chosen on real validation objects with ``python -m
    physgm.train.evaluate --prior-sweep [--prior-temperature T]``); ``logvar_offsets``
    the (E, nu) calibration of the physics head and ``material_temperature`` the temperature of its
    material logits (both from ``python -m physgm.train.calibrate`` on a validation split).
    """
    hparams = ckpt.hparams
    state = {PREFIX + k: v.detach().clone() for k, v in ckpt.state.items()}
    kept = {k: hparams[k] for k in KEEP_HPARAMS if k in hparams}
    head = {}
    if prior_weight is not None:
        config = PhysGMConfig.from_dict(kept["model"]).with_prior_weight(prior_weight)
        head["semantic_prior_weight"] = config.physics_head.semantic_prior_weight
    if prior_temperature is not None:
        if not prior_temperature > 0:
            raise ValueError(f"--prior-temperature must be > 0, got {prior_temperature}")
        head["semantic_prior_temperature"] = float(prior_temperature)
    if material_temperature is not None:
        if not material_temperature > 0:
            raise ValueError(f"--material-temperature must be > 0, got {material_temperature}")
        head["material_temperature"] = float(material_temperature)
    if logvar_offsets is not None:
        head["E_logvar_offset"], head["nu_logvar_offset"] = (float(x) for x in logvar_offsets)
    if head:
        model = copy.deepcopy(dict(kept["model"]))
        model["physics_head"] = {**model.get("physics_head", {}), **head}
        kept["model"] = model
    kept.setdefault("format_version", physgm.CHECKPOINT_FORMAT_VERSION)
    return {
        "hyper_parameters": kept,
        "state_dict": state,
        "global_step": ckpt.raw.get("global_step"),
        "epoch": ckpt.raw.get("epoch"),
        "pytorch-lightning_version": ckpt.raw.get("pytorch-lightning_version"),
        "physgm": {
            "version": physgm.__version__,
            "source": source,
            "git_revision": git_revision(Path(__file__).parent),
            "exported_at": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "recipe": recipe,
            "metrics": metrics,
        },
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m physgm.train.export", description=__doc__.split("\n")[0])
    p.add_argument("ckpt", type=Path, help="Lightning checkpoint written by train.py")
    p.add_argument("out", type=Path, help="slim checkpoint to write")
    p.add_argument("--recipe", default=None, help="the command(s) that trained it, stored in the file")
    p.add_argument(
        "--metrics", type=Path, default=None, help="JSON of measured metrics to store (e.g. evaluate's)"
    )
    p.add_argument(
        "--prior-weight", type=float, default=None, help="semantic prior weight w of the exported model"
    )
    p.add_argument(
        "--prior-temperature",
        type=float,
        default=None,
        help="temperature T of the ImageNet classifier in the semantic prior of the exported model",
    )
    p.add_argument(
        "--logvar-offsets",
        type=float,
        nargs=2,
        default=None,
        metavar=("E", "NU"),
        help="calibration added to the physics head's log-variances (python -m physgm.train.calibrate)",
    )
    p.add_argument(
        "--material-temperature",
        type=float,
        default=None,
        help="temperature of the material logits of the exported model (python -m physgm.train.calibrate)",
    )
    a = p.parse_args(argv)
    if not a.ckpt.is_file():
        raise SystemExit(f"checkpoint {a.ckpt} not found")
    metrics = json.loads(a.metrics.read_text()) if a.metrics else None
    try:
        out = slim(
            read_checkpoint(a.ckpt),
            str(a.ckpt),
            a.recipe,
            metrics,
            a.prior_weight,
            a.logvar_offsets,
            a.prior_temperature,
            a.material_temperature,
        )
    except (UserError, ValueError) as err:
        raise SystemExit(str(err)) from None
    a.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = a.out.with_name(a.out.name + ".tmp")
    torch.save(out, tmp)
    tmp.replace(a.out)  # atomic: never a half-written checkpoint under the final name
    size = a.out.stat().st_size / 2**20
    print(
        json.dumps(
            {
                "out": str(a.out),
                "megabytes": round(size, 2),
                "weights": len(out["state_dict"]),
                "parameters": sum(v.numel() for v in out["state_dict"].values()),
                "global_step": out["global_step"],
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
