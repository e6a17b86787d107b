"""physgm's MobileNetV2 against torchvision's (its slow twin here: the same network, imported)."""

from __future__ import annotations

import torch
import torchvision

from physgm.model import pretrained
from physgm.model.mobilenet_v2 import MobileNetV2


def _twins() -> tuple[torch.nn.Module, torch.nn.Module]:
    state = torch.load(pretrained.mobilenet_v2_weights_path(), map_location="cpu", weights_only=True)
    theirs = torchvision.models.mobilenet_v2(weights=None)
    theirs.load_state_dict(state, strict=True)
    return pretrained.load_mobilenet_v2(), theirs.eval()


def test_same_parameters_and_buffers_as_torchvision():
    ours, theirs = MobileNetV2().state_dict(), torchvision.models.mobilenet_v2(weights=None).state_dict()
    assert {k: v.shape for k, v in ours.items()} == {k: v.shape for k, v in theirs.items()}


def test_every_stage_and_the_logits_equal_torchvision_on_the_shipped_weights():
    ours, theirs = _twins()
    x = torch.randn(2, 3, 160, 128)
    with torch.no_grad():
        a, b = x, x
        for i, (mine, ref) in enumerate(zip(ours.features, theirs.features, strict=True)):
            a, b = mine(a), ref(b)
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5, msg=f"features[{i}]")
        torch.testing.assert_close(ours(x), theirs(x), rtol=1e-5, atol=1e-5)


def test_shipped_class_names_are_torchvision_s_list():
    names = torchvision.models.MobileNet_V2_Weights.IMAGENET1K_V1.meta["categories"]
    assert pretrained.imagenet_categories() == list(names)
