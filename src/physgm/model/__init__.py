"""The PhysGM model: posed views -> per-pixel Gaussians + physics posterior (nn.Modules only).

Layout: ``config`` (dataclasses), ``encoder`` (per-view timm ViT / DINOv3), ``backbone`` (camera
tokens, global tokens, joint transformer), ``gaussian_head`` (DPT), ``physics_head`` and
``posterior`` (material / E / nu distribution), ``physgm`` (the assembled model).
"""

from physgm.model.config import (
    BackboneConfig,
    EncoderConfig,
    GaussianHeadConfig,
    PhysGMConfig,
    PhysicsHeadConfig,
)
from physgm.model.gaussian_head import GaussianPrediction
from physgm.model.physgm import PhysGM, PhysGMOutput, build_physgm, load_physgm
from physgm.model.posterior import PhysicsPosterior, PhysicsSample

__all__ = [
    "BackboneConfig",
    "EncoderConfig",
    "GaussianHeadConfig",
    "GaussianPrediction",
    "PhysGM",
    "PhysGMConfig",
    "PhysGMOutput",
    "PhysicsHeadConfig",
    "PhysicsPosterior",
    "PhysicsSample",
    "build_physgm",
    "load_physgm",
]
