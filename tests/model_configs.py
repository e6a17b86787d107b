"""The model configs the tests build: the shipped model's code paths at sizes that run in milliseconds.

Two sizes, every dimension of the second twice the first's:
- ``tiny_config``: width 32, for tests that run many forwards (DPO, rollouts, warm starts);
- ``small_config``: width 64, for the model and pipeline tests.

Both take 32 px inputs in 8 px patches through a one-block ViT encoder and four backbone blocks, each
feeding the DPT head. Import them as ``from tests.model_configs import tiny_config``.
"""

from __future__ import annotations

from physgm.model import BackboneConfig, EncoderConfig, GaussianHeadConfig, PhysGMConfig


def _config(unit: int, width: int | None, geometry_blocks: int, head: dict) -> PhysGMConfig:
    encoder = EncoderConfig(img_size=32, patch_size=8, embed_dim=4 * unit, depth=1, num_heads=2)
    backbone = BackboneConfig(
        encoder=encoder,
        width=4 * unit if width is None else width,
        depth=4,
        head_dim=2 * unit,
        camera_dim=unit,
        camera_hidden=2 * unit,
        out_layers=(0, 1, 2, 3),
        geometry_blocks=geometry_blocks,
    )
    gaussian_head = GaussianHeadConfig(
        features=unit, layer_channels=(unit, unit, 2 * unit, 2 * unit), hidden=unit, **head
    )
    return PhysGMConfig(backbone=backbone, gaussian_head=gaussian_head)


def tiny_config(*, width: int | None = None, geometry_blocks: int = 0, **head) -> PhysGMConfig:
    """Backbone width 32 (or ``width``); ``head`` sets fields of the Gaussian head's config."""
    return _config(8, width, geometry_blocks, head)


def small_config(**head) -> PhysGMConfig:
    """Backbone width 64; ``head`` sets fields of the Gaussian head's config."""
    return _config(16, None, 0, head)
