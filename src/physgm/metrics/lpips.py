"""LPIPS from the ``lpips`` package, with its ImageNet backbone loaded from a local file only.

The package ships its small linear heads but downloads the torchvision backbone on first use;
physgm never downloads. The backbone comes from ``backbone_path`` or torchvision's usual cache
file, and a missing file stops with a message saying where to put it or how to switch LPIPS off,
never a silently random backbone. ``net="mobilenet"`` needs no file beyond the CPU model's own
encoder: LPIPS's baseline recipe on the frozen MobileNetV2 (``physgm.metrics.perceptual``).
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import torch
from torch import Tensor, nn

# torchvision checkpoint file names of the LPIPS backbones (what torchvision would download).
BACKBONE_FILES = {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth"}


def default_backbone_path(net: str) -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints" / BACKBONE_FILES[net]


def load_lpips(net: str = "alex", backbone_path: str | Path | None = None) -> nn.Module:
    """An LPIPS network in eval mode with frozen weights.

    Args:
        net: "alex" or "vgg" (the ``lpips`` package's), or "mobilenet" (``FeatureDistance``).
        backbone_path: torchvision ImageNet weights of that network; default: torchvision's cache
            (for "mobilenet", the file the weights package ships).
    Raises:
        FileNotFoundError: the backbone file is not on disk (the message says what to do).
    """
    if net == "mobilenet":
        from physgm.metrics.perceptual import FeatureDistance

        return FeatureDistance(None if backbone_path is None else str(backbone_path)).eval()
    import lpips

    if net not in BACKBONE_FILES:
        raise ValueError(f"LPIPS net must be one of {[*sorted(BACKBONE_FILES), 'mobilenet']}, got {net!r}")
    path = Path(backbone_path) if backbone_path else default_backbone_path(net)
    if not path.is_file():
        raise FileNotFoundError(
            f"LPIPS needs the ImageNet weights of its {net} backbone and physgm never downloads them. Put "
            f"the torchvision file {BACKBONE_FILES[net]} at {path} (or set "
            "stage.loss.lpips_backbone_path=/path/to/file), or switch the LPIPS term off with "
            "stage.loss.lpips=0."
        )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # torchvision's 'pretrained' deprecation notice
        model = lpips.LPIPS(net=net, pnet_rand=True, verbose=False)
    state = torch.load(path, map_location="cpu", weights_only=True)
    features = {k.removeprefix("features."): v for k, v in state.items() if k.startswith("features.")}
    mapped = {}
    for key in model.net.state_dict():
        index_and_param = re.sub(r"^slice\d+\.", "", key)  # "slice2.3.weight" -> "3.weight"
        if index_and_param not in features:
            raise ValueError(
                f"{path} does not look like torchvision {net} weights: no features.{index_and_param}"
            )
        mapped[key] = features[index_and_param]
    model.net.load_state_dict(mapped)
    return model.eval().requires_grad_(False)


def lpips_distance(model: nn.Module, pred: Tensor, target: Tensor) -> Tensor:
    """Mean LPIPS between images [..., 3, H, W] in [0, 1]."""
    shape = pred.shape
    return model(pred.reshape(-1, *shape[-3:]), target.reshape(-1, *shape[-3:]), normalize=True).mean()
