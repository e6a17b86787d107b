"""Reading a PhysGM checkpoint, with a compatibility check that names the problem, and writing one.

Checkpoints are the ones Lightning writes for ``LitPretrain`` / ``LitDPO`` (or ``save_checkpoint``
and ``physgm.train.export`` write in the same layout): a dict with ``hyper_parameters.model``
(``PhysGMConfig.to_dict()``) and ``state_dict`` whose model weights carry the ``model.`` prefix.
Every reader (the pipeline, the DPO stage's initial model, evaluation, export, benchmarks) goes
through ``read_checkpoint`` / ``load_model``, so each finds the same problems with the same
message: the optional ``hyper_parameters.format_version``, the stored model config (unknown keys
mean a different physgm version), the state-dict keys and shapes against a freshly built model,
and non-finite weights.
"""

from __future__ import annotations

import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from physgm import CHECKPOINT_FORMAT_VERSION
from physgm.errors import UserError
from physgm.model.config import PhysGMConfig
from physgm.model.physgm import PhysGM
from physgm.resources import packaged_checkpoint

PREFIX = "model."
REPO_ROOT = Path(__file__).resolve().parents[3]  # relative checkpoint paths also resolve here
# what torch.load raises on a file that is not a readable checkpoint
_READ_ERRORS = (
    pickle.UnpicklingError,
    EOFError,
    zipfile.BadZipFile,
    RuntimeError,
    OSError,
    ValueError,
    AttributeError,
    ModuleNotFoundError,
    IndexError,
)


def resolve_checkpoint(path: Path | str) -> Path:
    """``path`` itself if it exists, else (for a relative path) the same path under the repo root,
    else the copy shipped in the package (``checkpoints/physgm_tiny.ckpt``), so the default is
    found from any working directory, in a checkout or an installed wheel."""
    path = Path(path)
    if path.is_file() or path.is_absolute():
        return path
    if (REPO_ROOT / path).is_file():
        return REPO_ROOT / path
    return packaged_checkpoint(path) or path


def missing_checkpoint_message(path: Path) -> str:
    return (
        f"no PhysGM checkpoint at {path}. Train one with `python train.py experiment=tiny_cpu` "
        f"(then copy its checkpoints/last.ckpt to {path}) or pass ckpt=path/to/model.ckpt"
    )


def _list(items: list[str], limit: int = 3) -> str:
    more = f" and {len(items) - limit} more" if len(items) > limit else ""
    return ", ".join(items[:limit]) + more


@dataclass
class Checkpoint:
    """A checkpoint file, read and checked for its layout (not yet against a model)."""

    path: Path
    hparams: dict  # hyper_parameters: model (PhysGMConfig.to_dict()), renderer, inputs, format_version
    state: dict[str, Tensor]  # the model's weights, without Lightning's "model." prefix
    raw: dict  # the whole file (global_step, Lightning's version, export record, optimiser states)

    @property
    def format_version(self) -> int:
        return self.hparams.get("format_version", 1)

    def summary(self) -> dict:
        """What a run report records about the checkpoint."""
        return {
            "path": str(self.path),
            "format_version": self.format_version,
            "lightning_version": self.raw.get("pytorch-lightning_version"),
            "global_step": self.raw.get("global_step"),
        }


def read_checkpoint(path: Path | str) -> Checkpoint:
    """The checkpoint at ``path`` (see ``resolve_checkpoint``), with its layout and version checked.

    Raises:
        UserError: the file is missing, unreadable, not a physgm checkpoint, holds no model
            weights, or has another format version.
    """
    path = resolve_checkpoint(path)
    if not path.is_file():
        raise UserError(missing_checkpoint_message(path))
    try:
        # weights_only=False: Lightning stores plain-Python hyper-parameters next to the tensors.
        raw = torch.load(path, map_location="cpu", weights_only=False)
    except _READ_ERRORS as err:
        raise UserError(
            f"{path} is not a readable PyTorch checkpoint ({type(err).__name__}: {str(err)[:120]})"
        ) from None
    if (
        not isinstance(raw, dict)
        or not isinstance(raw.get("hyper_parameters"), dict)
        or "model" not in raw["hyper_parameters"]
    ):
        raise UserError(
            f"{path} is not a physgm checkpoint: it has no hyper_parameters.model (train one with `python "
            "train.py`)"
        )
    if not isinstance(raw.get("state_dict"), dict):
        raise UserError(f"{path} is not a physgm checkpoint: it has no state_dict")
    ckpt = Checkpoint(
        path=path,
        hparams=raw["hyper_parameters"],
        state={k.removeprefix(PREFIX): v for k, v in raw["state_dict"].items() if k.startswith(PREFIX)},
        raw=raw,
    )
    if ckpt.format_version != CHECKPOINT_FORMAT_VERSION:
        raise UserError(
            f"{path} has checkpoint format version {ckpt.format_version!r}, this physgm reads version "
            f"{CHECKPOINT_FORMAT_VERSION}; use the physgm release that wrote it, or retrain"
        )
    if not ckpt.state:
        raise UserError(f"{path} holds no model weights (no state_dict keys starting with '{PREFIX}')")
    return ckpt


def load_model(path: Path | str, device: str = "cpu") -> tuple[PhysGM, Checkpoint]:
    """The checkpoint's PhysGM in eval mode on ``device``, and the checkpoint it came from.

    The check is always the strict one: the weights must match a freshly built model key for key
    and shape for shape, and be finite. The looser loader the training tools had (no version or
    finite check) served no caller: every one of them runs the model, and a missing weight, a
    wrong shape or a NaN only fails later with a worse message.

    Raises:
        UserError: as ``read_checkpoint``, or the weights do not match this physgm's model (the
            message says which part does not match), or some are non-finite.
    """
    ckpt = read_checkpoint(path)
    path = ckpt.path
    try:
        config = PhysGMConfig.from_dict(dict(ckpt.hparams["model"] or {}))
        model = PhysGM(config, load_pretrained=False)
    except (ValueError, TypeError, KeyError) as err:
        raise UserError(
            f"{path} was written by an incompatible physgm version: its model config does not load ({err})"
        ) from None
    state = ckpt.state
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    shapes = [
        f"{k} {tuple(state[k].shape)} != {tuple(v.shape)}"
        for k, v in expected.items()
        if k in state and tuple(state[k].shape) != tuple(v.shape)
    ]
    problems = []
    if missing:
        problems.append(f"{len(missing)} weights missing ({_list(missing)})")
    if unexpected:
        problems.append(f"{len(unexpected)} unknown weights ({_list(unexpected)})")
    if shapes:
        problems.append(f"{len(shapes)} weights of the wrong shape ({_list(shapes)})")
    if problems:
        raise UserError(
            f"{path} does not match this physgm version's model: {'; '.join(problems)}. "
            "Use the physgm release that wrote it, or retrain"
        )
    bad = [k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise UserError(
            f"{path} has non-finite weights ({_list(bad)}); the training run that wrote it diverged"
        )
    model.load_state_dict(state, strict=True)
    return model.to(device).eval(), ckpt


def input_size(model: PhysGM, hparams: dict | None = None) -> int:
    """Square input size (px) the model was trained at, a multiple of its patch size.

    DPO checkpoints record the input resolution they trained on (``hyper_parameters.inputs``);
    otherwise the encoder's position-embedding grid ``img_size`` is the training size.
    """
    inputs = (hparams or {}).get("inputs") or {}
    size = inputs.get("input_resolution") or model.config.backbone.encoder.img_size
    p = model.patch_size
    return max(p, round(int(size) / p) * p)


def save_checkpoint(model: PhysGM, path: Path, global_step: int = 0) -> None:
    """Write ``model`` in the layout Lightning writes for ``LitPretrain`` (weights only, no optimiser).

    ``LitPretrain.load_from_checkpoint`` and ``load_model`` both read the result; used to ship or
    export a model and, in tests and benchmarks, to make a randomly initialised checkpoint.
    """
    import lightning

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ckpt = {
        "epoch": 0,
        "global_step": global_step,
        "pytorch-lightning_version": lightning.__version__,
        "state_dict": {PREFIX + k: v.detach().cpu() for k, v in model.state_dict().items()},
        "loops": {},
        "callbacks": {},
        "optimizer_states": [],
        "lr_schedulers": [],
        "hparams_name": "kwargs",
        "hyper_parameters": {"model": model.config.to_dict()},
    }
    torch.save(ckpt, path)
