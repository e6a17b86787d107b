"""PhysGM: posed views -> per-pixel 3D Gaussians + a physics posterior, in one forward pass."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from torch import Tensor, nn

from physgm.cameras import Cameras, plucker_rays
from physgm.model.backbone import Backbone
from physgm.model.cnn_encoder import LEVEL_CHANNELS, ImageFeatures, MobileNetEncoder
from physgm.model.config import PhysGMConfig
from physgm.model.domain_gate import DomainGate
from physgm.model.gaussian_head import GaussianHead, GaussianPrediction
from physgm.model.physics_head import POOLED_DIM, PhysicsHead, fuse_material_logits, pooled_features
from physgm.model.posterior import PhysicsPosterior
from physgm.model.semantic_prior import pool_views, semantic_log_prior


@dataclass
class PhysGMOutput:
    """What the model predicts for a batch of scenes."""

    gaussians: GaussianPrediction  # N = L * V * H * W Gaussians per scene (L layers), invalid ones flagged
    physics: PhysicsPosterior  # [B] posterior over material, log10 E, nu
    semantic_log_prior: Tensor | None = None  # [B, M] the ImageNet classes' material prior (CNN encoder)
    head_material_logits: Tensor | None = None  # [B, M] the physics head's alone, before the prior
    domain_real: Tensor | None = None  # [B] the domain gate's P(real object), when the model has one
    procedural_material_logits: Tensor | None = None  # [B, M] the procedural expert's, when there is one
    global_tokens: Tensor | None = None  # [B, G, D] the backbone's global tokens: all the physics head reads


class PhysGM(nn.Module):
    """Feed-forward physical Gaussian model.

    Args:
        config: sizes and output ranges; ``PhysGMConfig()`` is the tiny CPU model.
        load_pretrained: read the encoder's local pretrained weights (DINOv3); False when a
            checkpoint's state dict will overwrite them anyway.
    """

    def __init__(self, config: PhysGMConfig | None = None, load_pretrained: bool = True) -> None:
        super().__init__()
        self.config = config = config or PhysGMConfig()
        self.backbone = Backbone(config.backbone, load_pretrained)
        cnn = isinstance(self.backbone.encoder, MobileNetEncoder)
        skips = tuple(LEVEL_CHANNELS.values()) if cnn else None
        self.gaussian_head = GaussianHead(
            config.gaussian_head, config.backbone.width, self.backbone.patch_size, skips
        )
        if config.physics_head.material_input == "features" and not cnn:
            raise ValueError(
                "physics_head.material_input='features' reads the frozen CNN encoder's pyramid: it "
                f"needs backbone.encoder.kind='mobilenet_v2', got {config.backbone.encoder.kind!r}"
            )
        self.physics_head = PhysicsHead(
            config.physics_head, config.backbone.width, config.backbone.num_global_tokens
        )
        self.domain_gate = None
        if config.physics_head.domain_gate:
            if not cnn:
                raise ValueError(
                    "physics_head.domain_gate reads the frozen CNN encoder's pyramid: it needs "
                    f"backbone.encoder.kind='mobilenet_v2', got {config.backbone.encoder.kind!r}"
                )
            self.domain_gate = DomainGate()
        if config.physics_head.procedural_expert and self.domain_gate is None:
            raise ValueError(
                "physics_head.procedural_expert is mixed in by the domain gate: it needs "
                "physics_head.domain_gate (python -m physgm.train.fit_gate fits one)"
            )

    @property
    def patch_size(self) -> int:
        return self.backbone.patch_size

    def forward(
        self,
        images: Tensor,  # [B, V, 3, H, W] RGB in [0, 1]
        masks: Tensor,  # [B, V, 1, H, W] object mask in [0, 1]
        c2w: Tensor,  # [B, V, 4, 4] OpenCV camera-to-world
        Ks: Tensor,  # [B, V, 3, 3] pixel intrinsics
        features: ImageFeatures | None = None,  # [B, V, ...] cached frozen-encoder outputs of the views
    ) -> PhysGMOutput:
        """Predict Gaussians (one per in-mask input pixel) and the physics posterior.

        Any V >= 1 and any H, W that are multiples of the patch size work; the views of a scene
        attend to each other jointly. ``features`` (the frozen CNN encoder only) skips the encoder.
        """
        self._check_inputs(images, masks, c2w, Ks)
        b, v = images.shape[:2]
        out, plucker = self._backbone(images, c2w, Ks, features)
        directions = plucker[:, :, :3].permute(0, 1, 3, 4, 2)  # [B, V, H, W, 3] unit
        skips = out.features.levels() if out.features is not None else None
        gaussians = self.gaussian_head(
            out.patch_tokens, images, masks, c2w.to(images.dtype), Ks.to(images.dtype), directions, skips
        )
        log_prior = None
        if out.features is not None:  # the views show one object: one mixture of their ImageNet classes
            logits = (
                out.features.imagenet_logits.reshape(b, v, -1)
                / self.config.physics_head.semantic_prior_temperature
            )
            log_prior = semantic_log_prior(pool_views(logits, dim=1))
        cfg = self.config.physics_head
        pooled = gate = None
        if cfg.material_input == "features" or self.domain_gate is not None:
            per_view = pooled_features(out.features, b * v).reshape(b, v, POOLED_DIM)  # pooled once
            pooled = per_view.mean(1)  # = pooled_features(out.features, b)
            if self.domain_gate is not None:
                gate = self.domain_gate.scene_probability(per_view)
        head = self.physics_head(out.global_tokens, pooled)
        procedural = self.physics_head.procedural_logits(pooled)
        physics = self.fused_posterior(head, log_prior, gate, procedural)
        return PhysGMOutput(
            gaussians, physics, log_prior, head.material_logits, gate, procedural, out.global_tokens
        )

    def global_tokens(
        self,
        images: Tensor,  # [B, V, 3, H, W] RGB in [0, 1]
        c2w: Tensor,  # [B, V, 4, 4] OpenCV camera-to-world
        Ks: Tensor,  # [B, V, 3, 3] pixel intrinsics
        features: ImageFeatures | None = None,  # [B, V, ...] cached frozen-encoder outputs
    ) -> Tensor:  # [B, G, D]
        """The backbone's global tokens alone (no Gaussians): what the physics head reads."""
        return self._backbone(images, c2w, Ks, features)[0].global_tokens

    def _backbone(self, images: Tensor, c2w: Tensor, Ks: Tensor, features: ImageFeatures | None):
        """Backbone output and the views' Plücker rays [B, V, 6, H, W] (direction, moment)."""
        b, v, _, height, width = images.shape
        cameras = Cameras(
            c2w.reshape(b * v, 4, 4).to(images.dtype), Ks.reshape(b * v, 3, 3).to(images.dtype), width, height
        )
        plucker = plucker_rays(cameras).reshape(b, v, 6, height, width)
        return self.backbone(images, plucker, features), plucker

    def fused_posterior(
        self,
        head: PhysicsPosterior,  # [B] the physics head's own
        log_prior: Tensor | None,  # [B, M] semantic_log_prior, or None
        gate: Tensor | None,  # [B] the domain gate's P(real object), or None
        procedural: Tensor | None,  # [B, M] the procedural expert's logits, or None
    ) -> PhysicsPosterior:
        """The model's posterior from its physics head's: the material distribution fused with the
        semantic prior, the domain gate and the procedural expert at this model's w and temperature
        (``fuse_material_logits``). The DPO stage calls it on cached head inputs."""
        cfg = self.config.physics_head
        fused = fuse_material_logits(
            head.material_logits,
            log_prior,
            cfg.semantic_prior_weight,
            cfg.material_temperature,
            gate,
            procedural,
        )
        return dataclasses.replace(head, material_logits=fused)

    def encode_views(
        self,
        images: Tensor,  # [V, 3, H, W] one scene's input views in [0, 1]
        classifier_images: Tensor | None = None,  # [V, 3, h, w] the same views at a higher resolution
    ) -> ImageFeatures | None:  # [1, V, ...], or None for a ViT encoder
        """The frozen CNN encoder's features of one scene, its ImageNet classifier reading
        ``classifier_images`` when given; pass the result to ``forward`` as ``features``."""
        encoder = self.backbone.encoder
        if not isinstance(encoder, MobileNetEncoder):
            return None
        return encoder.encode(images, classifier_images).map(lambda t: t[None])

    def physics_parameters(self) -> Iterator[nn.Parameter]:
        """Parameters of the physics head: the only ones the DPO stage trains."""
        return self.physics_head.parameters()

    def backbone_parameters(self) -> Iterator[nn.Parameter]:
        """Everything but the physics head (encoder, backbone, Gaussian head): frozen during DPO."""
        head = {id(p) for p in self.physics_head.parameters()}
        return (p for p in self.parameters() if id(p) not in head)

    def _check_inputs(self, images: Tensor, masks: Tensor, c2w: Tensor, Ks: Tensor) -> None:
        if images.ndim != 5 or images.shape[2] != 3:
            raise ValueError(f"images must have shape [B, V, 3, H, W], got {tuple(images.shape)}")
        b, v, _, height, width = images.shape
        expected = {
            "masks": (masks, (b, v, 1, height, width)),
            "c2w": (c2w, (b, v, 4, 4)),
            "Ks": (Ks, (b, v, 3, 3)),
        }
        for name, (tensor, shape) in expected.items():
            if tuple(tensor.shape) != shape:
                raise ValueError(
                    f"{name} must have shape {list(shape)} to match images {tuple(images.shape)}, got "
                    f"{tuple(tensor.shape)}"
                )
        p = self.patch_size
        if height % p or width % p:
            raise ValueError(
                f"image size {height}x{width} must be a multiple of the patch size {p}; resize the views"
            )


def build_physgm(**config: Any) -> PhysGM:
    """Hydra entry (``_target_: physgm.model.build_physgm``): nested config mapping -> ``PhysGM``."""
    return PhysGM(PhysGMConfig.from_dict(config))


def load_physgm(config: Mapping[str, Any], state_dict: Mapping[str, Tensor] | None = None) -> PhysGM:
    """Rebuild a model from a checkpoint's ``PhysGMConfig.to_dict()`` and (optionally) its weights."""
    model = PhysGM(PhysGMConfig.from_dict(config), load_pretrained=state_dict is None)
    if state_dict is not None:
        model.load_state_dict(state_dict, strict=True)
    return model
