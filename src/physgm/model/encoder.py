"""Per-view image encoders: a timm ViT from scratch, DINOv3 from a local file, frozen ImageNet MobileNetV2.

Both turn each view into one token per ``patch_size`` x ``patch_size`` patch; the joint backbone
(``physgm.model.backbone``) then mixes the views. Nothing here ever downloads weights: timm models
are built with ``pretrained=False`` and DINOv3 weights come from the file named in the config.
timm is imported only by the builders that use it: it takes seconds to import, and the frozen CNN
encoder, the CPU default, does not need it.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor, nn

from physgm.model.cnn_encoder import MobileNetEncoder
from physgm.model.config import EncoderConfig
from physgm.model.pretrained import IMAGENET_MEAN, IMAGENET_STD

# DINOv3 was trained on ImageNet-normalised inputs (IMAGENET_MEAN, IMAGENET_STD); the scratch ViT
# uses the same so that the encoders are interchangeable behind one interface.

# DINOv3 architectures the paper uses (timm names); any other timm "*dinov3*" model also builds.
DINOV3_ARCHS = {"vits16": "vit_small_patch16_dinov3", "vitl16": "vit_large_patch16_dinov3"}

_CONFIG_KEY = "model.backbone.encoder.weights"


class ImageEncoder(nn.Module):
    """Wraps a timm ViT: images in [0, 1] -> patch tokens, prefix (cls/register) tokens dropped."""

    def __init__(self, vit: nn.Module, patch_size: int, embed_dim: int, freeze: bool) -> None:
        super().__init__()
        self.vit = vit
        self.patch_size = patch_size
        self.embed_dim = embed_dim
        self.frozen = freeze
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        if freeze:
            self.vit.requires_grad_(False)
            self.vit.eval()

    def train(self, mode: bool = True) -> ImageEncoder:
        super().train(mode)
        if self.frozen:
            self.vit.eval()  # a frozen encoder never changes behaviour with the trainer's mode
        return self

    def forward(
        self,
        images: Tensor,  # [B, 3, H, W] RGB in [0, 1]
    ) -> Tensor:  # [B, (H / p) * (W / p), D_enc]
        """Encode images into row-major patch tokens."""
        h, w = images.shape[-2:]
        if h % self.patch_size or w % self.patch_size:
            raise ValueError(
                f"image size {h}x{w} is not a multiple of the encoder patch size {self.patch_size}; "
                "resize or crop the input views"
            )
        x = (images - self.mean) / self.std
        with torch.set_grad_enabled(torch.is_grad_enabled() and not self.frozen):
            tokens = self.vit.forward_features(x)  # [B, prefix + L, D_enc]
        return tokens[:, self.vit.num_prefix_tokens :]


def build_vit(cfg: EncoderConfig, load_pretrained: bool = True) -> ImageEncoder:
    """A timm VisionTransformer from scratch, sized by the config (it has no pretrained weights)."""
    if cfg.embed_dim % cfg.num_heads:
        raise ValueError(f"encoder embed_dim {cfg.embed_dim} is not divisible by num_heads {cfg.num_heads}")
    import timm

    vit = timm.models.vision_transformer.VisionTransformer(
        img_size=cfg.img_size,
        patch_size=cfg.patch_size,
        embed_dim=cfg.embed_dim,
        depth=cfg.depth,
        num_heads=cfg.num_heads,
        num_classes=0,
        global_pool="",
        class_token=False,  # the joint backbone has its own global tokens
        dynamic_img_size=True,  # any H, W that are multiples of patch_size
    )
    return ImageEncoder(vit, cfg.patch_size, cfg.embed_dim, cfg.freeze)


def build_timm(cfg: EncoderConfig, load_pretrained: bool = True) -> ImageEncoder:
    """Any timm ViT named by ``cfg.arch``; ``cfg.pretrained``: timm fetches its weights (needs a network).

    physgm never downloads anything itself: this is for a user who has the network (or timm's
    cache filled). ``load_pretrained=False`` (a checkpoint supplies the weights) never fetches.
    """
    if not cfg.arch:
        raise ValueError("encoder.kind=timm needs encoder.arch, a timm ViT name (e.g. vit_small_patch16_224)")
    import timm

    vit = timm.create_model(
        cfg.arch,
        pretrained=cfg.pretrained and load_pretrained,
        num_classes=0,
        img_size=cfg.img_size,
        dynamic_img_size=True,
    )
    actual = (vit.patch_embed.patch_size[0], vit.embed_dim)
    if actual != (cfg.patch_size, cfg.embed_dim):
        raise ValueError(
            f"{cfg.arch} has patch_size={actual[0]}, embed_dim={actual[1]}, but the config says "
            f"patch_size={cfg.patch_size}, embed_dim={cfg.embed_dim}; fix model.backbone.encoder"
        )
    return ImageEncoder(vit, cfg.patch_size, cfg.embed_dim, cfg.freeze)


def build_dinov3(cfg: EncoderConfig, load_pretrained: bool = True) -> ImageEncoder:
    """The timm DINOv3 architecture named by ``cfg.arch`` with weights from the local file ``cfg.weights``.

    ``load_pretrained=False`` builds the architecture only (a checkpoint will supply the weights).
    """
    import timm

    arch = DINOV3_ARCHS.get(cfg.arch, cfg.arch)
    available = timm.list_models("*dinov3*")
    if arch not in available:
        raise ValueError(
            f"unknown DINOv3 architecture {cfg.arch!r}; timm {timm.__version__} provides {available}"
        )
    path = _check_weights_path(cfg.weights, arch) if load_pretrained else None
    vit = timm.create_model(arch, pretrained=False, num_classes=0, img_size=cfg.img_size)
    if path is not None:
        load_dinov3_weights(vit, path)
    actual = (vit.patch_embed.patch_size[0], vit.embed_dim, len(vit.blocks))
    if actual != (cfg.patch_size, cfg.embed_dim, cfg.depth):
        raise ValueError(
            f"{arch} has patch_size={actual[0]}, embed_dim={actual[1]}, depth={actual[2]}, but the config "
            f"says patch_size={cfg.patch_size}, embed_dim={cfg.embed_dim}, depth={cfg.depth}; fix "
            "model.backbone.encoder"
        )
    return ImageEncoder(vit, cfg.patch_size, cfg.embed_dim, cfg.freeze)


def _check_weights_path(weights: str | None, arch: str) -> Path:
    hint = (
        f"DINOv3 weights are never downloaded. Get the {arch} checkpoint (Meta's original .pth from "
        "https://github.com/facebookresearch/dinov3, or timm's model.safetensors from the Hugging Face hub "
        f"repo timm/{arch}.lvd1689m), put it for example under checkpoints/dinov3/, and set "
        f"{_CONFIG_KEY}=/path/to/file (.pth or .safetensors)."
    )
    if not weights:
        raise FileNotFoundError(f"no DINOv3 weights file configured ({_CONFIG_KEY} is empty). {hint}")
    path = Path(weights).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"DINOv3 weights file {str(path)!r} does not exist. {hint}")
    return path


def load_dinov3_weights(vit: nn.Module, path: str | Path) -> None:
    """Strictly load a DINOv3 state dict (Meta or timm key layout) from a local file into ``vit``."""
    path = Path(path)
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        state = load_file(str(path), device="cpu")
    else:
        state = torch.load(path, map_location="cpu", weights_only=True)
    from timm.models.eva import checkpoint_filter_fn

    # Meta checkpoints name registers "storage_tokens", layer scales "ls1.gamma", ...; timm's filter
    # renames them and passes timm-layout dicts through unchanged.
    state = checkpoint_filter_fn(state, vit)
    missing, unexpected = _key_mismatch(vit.state_dict(), state)
    if missing or unexpected:
        raise RuntimeError(
            f"DINOv3 weights in {str(path)!r} do not match the timm architecture "
            f"{vit.pretrained_cfg.get('architecture', type(vit).__name__)!r}: "
            f"{len(missing)} missing keys (e.g. {missing[:5]}), {len(unexpected)} unexpected keys "
            f"(e.g. {unexpected[:5]}). Check that model.backbone.encoder.arch matches the checkpoint "
            "(e.g. vit_large_patch16_dinov3 vs vit_large_patch16_dinov3_qkvb) and that the file is a "
            "Meta or timm DINOv3 backbone (Hugging Face transformers layouts are not supported)."
        )
    vit.load_state_dict(state, strict=True)


def _key_mismatch(expected: dict[str, Tensor], got: dict[str, Tensor]) -> tuple[list[str], list[str]]:
    missing = sorted(set(expected) - set(got))
    unexpected = sorted(set(got) - set(expected))
    wrong = [k for k in set(expected) & set(got) if tuple(expected[k].shape) != tuple(got[k].shape)]
    return missing + sorted(f"{k} (shape)" for k in wrong), unexpected


def build_mobilenet_v2(cfg: EncoderConfig, load_pretrained: bool = True) -> MobileNetEncoder:
    """Frozen ImageNet MobileNetV2 (``physgm.model.cnn_encoder``); ``cfg.weights`` overrides its file.

    Its weights are read from the file even when a checkpoint is loaded: checkpoints leave them out.
    """
    if (cfg.patch_size, cfg.embed_dim) != (
        MobileNetEncoder.patch_size,
        MobileNetEncoder.embed_dim,
    ) or not cfg.freeze:
        raise ValueError(
            f"encoder.kind=mobilenet_v2 is frozen with patch_size={MobileNetEncoder.patch_size} and "
            f"embed_dim={MobileNetEncoder.embed_dim}; the config says patch_size={cfg.patch_size}, "
            f"embed_dim={cfg.embed_dim}, freeze={cfg.freeze}: fix model.backbone.encoder"
        )
    return MobileNetEncoder(cfg.weights)


# Registry: EncoderConfig.kind -> builder. Adding an encoder is one entry here.
ENCODERS: dict[str, Callable[[EncoderConfig, bool], nn.Module]] = {
    "vit": build_vit,
    "timm": build_timm,
    "dinov3": build_dinov3,
    "mobilenet_v2": build_mobilenet_v2,
}


def build_encoder(cfg: EncoderConfig, load_pretrained: bool = True) -> ImageEncoder | MobileNetEncoder:
    """Build the image encoder named by ``cfg.kind`` (``load_pretrained``: read local weights if any)."""
    if cfg.kind not in ENCODERS:
        raise ValueError(f"unknown encoder kind {cfg.kind!r}; choose one of {sorted(ENCODERS)}")
    return ENCODERS[cfg.kind](cfg, load_pretrained)
