"""Loading a PhysGM checkpoint for inference, with a compatibility check that names the problem.

Checkpoints are the ones Lightning writes for ``LitPretrain`` / ``LitDPO``: a dict with
``hyper_parameters.model`` (``PhysGMConfig.to_dict()``) and ``state_dict`` whose model weights
carry the ``model.`` prefix. Compatibility is checked in three steps, each with its own message:
the optional ``hyper_parameters.format_version``, the stored model config (unknown keys mean a
different physgm version), and the state-dict keys and shapes against a freshly built model.
"""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path

import torch

from physgm import CHECKPOINT_FORMAT_VERSION
from physgm.model.config import PhysGMConfig
from physgm.model.physgm import PhysGM
from physgm.pipeline.errors import UserError
from physgm.resources import packaged_checkpoint

PREFIX = "model."
REPO_ROOT = Path(__file__).resolve().parents[3]  # relative checkpoint paths also resolve here


def resolve_checkpoint(path: Path) -> Path:
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


def load_model(path: Path, device: str = "cpu") -> tuple[PhysGM, dict]:
    """The checkpoint's PhysGM in eval mode on ``device`` and a short description of the file.

    Raises:
        UserError: the file is missing, unreadable, not a physgm checkpoint, or from an
            incompatible version (the message says which part does not match).
    """
    path = resolve_checkpoint(path)
    if not path.is_file():
        raise UserError(missing_checkpoint_message(path))
    try:
        # weights_only=False: Lightning stores plain-Python hyper-parameters next to the tensors.
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except (
        pickle.UnpicklingError,
        EOFError,
        zipfile.BadZipFile,
        RuntimeError,
        OSError,
        ValueError,
        AttributeError,
        ModuleNotFoundError,
        IndexError,
    ) as err:
        raise UserError(
            f"{path} is not a readable PyTorch checkpoint ({type(err).__name__}: {str(err)[:120]})"
        ) from None
    if (
        not isinstance(ckpt, dict)
        or not isinstance(ckpt.get("hyper_parameters"), dict)
        or "model" not in ckpt["hyper_parameters"]
    ):
        raise UserError(
            f"{path} is not a physgm checkpoint: it has no hyper_parameters.model (train one with `python "
            "train.py`)"
        )
    if not isinstance(ckpt.get("state_dict"), dict):
        raise UserError(f"{path} is not a physgm checkpoint: it has no state_dict")
    hparams = ckpt["hyper_parameters"]
    version = hparams.get("format_version", 1)
    if version != CHECKPOINT_FORMAT_VERSION:
        raise UserError(
            f"{path} has checkpoint format version {version!r}, this physgm reads version "
            f"{CHECKPOINT_FORMAT_VERSION}; use the physgm release that wrote it, or retrain"
        )
    try:
        config = PhysGMConfig.from_dict(dict(hparams["model"] or {}))
        model = PhysGM(config, load_pretrained=False)
    except (ValueError, TypeError, KeyError) as err:
        raise UserError(
            f"{path} was written by an incompatible physgm version: its model config does not load ({err})"
        ) from None
    state = {k.removeprefix(PREFIX): v for k, v in ckpt["state_dict"].items() if k.startswith(PREFIX)}
    if not state:
        raise UserError(f"{path} holds no model weights (no state_dict keys starting with '{PREFIX}')")
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
    info = {
        "path": str(path),
        "format_version": version,
        "lightning_version": ckpt.get("pytorch-lightning_version"),
        "global_step": ckpt.get("global_step"),
        "input_size": input_size(model, hparams),
    }
    return model.to(device).eval(), info


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
