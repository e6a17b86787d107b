"""MobileNetV2 (Sandler et al. 2018) laid out as torchvision builds it, so its ImageNet state dict
loads with every key matched.

Written here instead of imported because importing torchvision imports all of its models and
``torch._dynamo``, about 3.5 s of start-up on a CPU, for one small network. Module names
(``features.<i>.conv.<j>``, ``classifier.1``) and the forward pass follow
``torchvision.models.mobilenet_v2``; ``tests/model/test_mobilenet_v2.py`` holds the two equal on
the shipped weights.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

# (expansion t, output channels c, repeats n, first stride s) of the paper's Table 2
INVERTED_RESIDUAL_SETTING = (
    (1, 16, 1, 1),
    (6, 24, 2, 2),
    (6, 32, 3, 2),
    (6, 64, 4, 2),
    (6, 96, 3, 1),
    (6, 160, 3, 2),
    (6, 320, 1, 1),
)
STEM_CHANNELS = 32
LAST_CHANNELS = 1280


class ConvBNReLU6(nn.Sequential):
    """Conv (no bias), batch norm, ReLU6: torchvision's ``Conv2dNormActivation`` with its defaults."""

    def __init__(self, inp: int, out: int, kernel: int = 3, stride: int = 1, groups: int = 1) -> None:
        super().__init__(
            nn.Conv2d(inp, out, kernel, stride, (kernel - 1) // 2, groups=groups, bias=False),
            nn.BatchNorm2d(out),
            nn.ReLU6(inplace=True),
        )


class InvertedResidual(nn.Module):
    """1x1 expansion (skipped when t = 1), 3x3 depthwise, linear 1x1 projection; a residual
    connection when the block keeps its size and channels."""

    def __init__(self, inp: int, out: int, stride: int, expand: int) -> None:
        super().__init__()
        hidden = inp * expand
        layers: list[nn.Module] = [] if expand == 1 else [ConvBNReLU6(inp, hidden, kernel=1)]
        layers += [
            ConvBNReLU6(hidden, hidden, stride=stride, groups=hidden),
            nn.Conv2d(hidden, out, 1, bias=False),
            nn.BatchNorm2d(out),
        ]
        self.conv = nn.Sequential(*layers)
        self.use_res_connect = stride == 1 and inp == out

    def forward(self, x: Tensor) -> Tensor:
        return x + self.conv(x) if self.use_res_connect else self.conv(x)


class MobileNetV2(nn.Module):
    """``features`` (19 stages: stem, 17 inverted residuals, 1x1 to 1280 channels) and
    ``classifier`` (dropout, linear to the 1000 ImageNet classes)."""

    def __init__(self, num_classes: int = 1000, dropout: float = 0.2) -> None:
        super().__init__()
        layers: list[nn.Module] = [ConvBNReLU6(3, STEM_CHANNELS, stride=2)]
        inp = STEM_CHANNELS
        for t, c, n, s in INVERTED_RESIDUAL_SETTING:
            for i in range(n):
                layers.append(InvertedResidual(inp, c, s if i == 0 else 1, t))
                inp = c
        layers.append(ConvBNReLU6(inp, LAST_CHANNELS, kernel=1))
        self.features = nn.Sequential(*layers)
        self.classifier = nn.Sequential(nn.Dropout(p=dropout), nn.Linear(LAST_CHANNELS, num_classes))

    def forward(self, x: Tensor) -> Tensor:  # [B, 3, H, W] ImageNet-normalised -> [B, classes] logits
        x = nn.functional.adaptive_avg_pool2d(self.features(x), 1)
        return self.classifier(torch.flatten(x, 1))
