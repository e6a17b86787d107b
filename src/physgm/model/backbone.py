"""Multi-view token backbone: image tokens + Plücker camera tokens, global tokens, joint transformer.

How the image encoder and the backbone relate: the encoder (timm ViT or DINOv3) sees one view at a
time and gives one token per patch. A small conv turns the view's Plücker ray map into a camera
token on the same patch grid. Per patch the two are concatenated and linearly projected to the
backbone width, as in the paper. Three learned global tokens are prepended and the tokens of all V
views attend jointly (sequence length 3 + V * h * w) in ``depth`` plain pre-norm transformer blocks.
Positions need no extra embedding: the encoder embeds positions within a view and the Plücker rays
tell apart every pixel of every view.

With ``geometry_blocks`` = N > 0 (not in the paper) the last N blocks exist twice: the global tokens
come out of the shared stack, the DPT head's patch tokens out of the Gaussian head's own copies, which
read the same input at the split. Training the copies changes the Gaussians and nothing the physics
head sees.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

from physgm.model.cnn_encoder import ImageFeatures, MobileNetEncoder
from physgm.model.config import BackboneConfig
from physgm.model.encoder import build_encoder
from physgm.model.transformer import Block


class PluckerEncoder(nn.Module):
    """Dense camera encoder: Plücker map [6, H, W] -> one camera token per patch."""

    def __init__(self, patch_size: int, hidden: int, out_dim: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(6, hidden, kernel_size=patch_size, stride=patch_size),  # patchify to the token grid
            nn.GELU(),
            nn.Conv2d(hidden, out_dim, kernel_size=1),
        )
        self.norm = nn.LayerNorm(out_dim)

    def forward(
        self,
        plucker: Tensor,  # [B, 6, H, W] (direction, moment)
    ) -> Tensor:  # [B, (H / p) * (W / p), out_dim]
        return self.norm(self.net(plucker).flatten(2).transpose(1, 2))


@dataclass
class BackboneOutput:
    """What the backbone hands to the heads."""

    global_tokens: Tensor  # [B, G, D] after the last block
    patch_tokens: list[Tensor]  # 4 x [B * V, h * w, D] after the blocks in cfg.out_layers
    features: ImageFeatures | None  # frozen CNN encoder's pyramid and logits, [B * V, ...] (None for ViTs)


class Backbone(nn.Module):
    """Encodes V posed views into global tokens and per-layer patch tokens."""

    def __init__(self, cfg: BackboneConfig, load_pretrained: bool = True) -> None:
        super().__init__()
        if cfg.width % cfg.head_dim:
            raise ValueError(f"backbone width {cfg.width} is not divisible by head_dim {cfg.head_dim}")
        if (
            len(cfg.out_layers) != 4
            or len(set(cfg.out_layers)) != 4
            or not all(0 <= i < cfg.depth for i in cfg.out_layers)
        ):
            raise ValueError(
                f"backbone.out_layers must be 4 distinct block indices in [0, {cfg.depth}), got "
                f"{list(cfg.out_layers)}"
            )
        self.cfg = cfg
        self.patch_size = cfg.encoder.patch_size
        self.encoder = build_encoder(cfg.encoder, load_pretrained)
        self.camera_encoder = PluckerEncoder(self.patch_size, cfg.camera_hidden, cfg.camera_dim)
        self.fuse = nn.Linear(cfg.encoder.embed_dim + cfg.camera_dim, cfg.width, bias=False)
        self.input_norm = nn.LayerNorm(cfg.width)
        # Random (not zero) init: identical global tokens would stay identical through every block.
        self.global_tokens = nn.Parameter(torch.randn(1, cfg.num_global_tokens, cfg.width) * 0.02)
        if not 0 <= cfg.geometry_blocks <= cfg.depth:
            raise ValueError(
                f"backbone.geometry_blocks must be in [0, {cfg.depth}], got {cfg.geometry_blocks}"
            )
        self.blocks = nn.ModuleList(_blocks(cfg, cfg.depth))
        # The Gaussian head's own copies of the last geometry_blocks blocks (none by default).
        self.geometry_blocks = nn.ModuleList(_blocks(cfg, cfg.geometry_blocks))
        for module in (self.camera_encoder, self.fuse, self.blocks, self.geometry_blocks):
            module.apply(_init_linear)  # never the (maybe pretrained) encoder

    def forward(
        self,
        images: Tensor,  # [B, V, 3, H, W] RGB in [0, 1]
        plucker: Tensor,  # [B, V, 6, H, W]
        features: ImageFeatures | None = None,  # [B, V, ...] cached CNN encoder outputs, or None
    ) -> BackboneOutput:
        """Run the encoder per view (or take its cached features) and the joint transformer.

        Patch tokens have the views folded into the batch and row-major patches.
        """
        b, v = images.shape[:2]
        if isinstance(self.encoder, MobileNetEncoder):
            if features is None:
                features = self.encoder.encode(images.flatten(0, 1))
            else:
                features = features.map(lambda t: t.flatten(0, 1).float())
            image_tokens = self.encoder.tokens(features)  # [B*V, L, D_enc]
        else:
            if features is not None:
                raise ValueError(
                    "cached image features are only used with the frozen CNN encoder "
                    "(encoder.kind=mobilenet_v2)"
                )
            image_tokens = self.encoder(images.flatten(0, 1))  # [B*V, L, D_enc]
        camera_tokens = self.camera_encoder(plucker.flatten(0, 1))  # [B*V, L, D_cam]
        tokens = self.fuse(torch.cat([image_tokens, camera_tokens], dim=-1))  # [B*V, L, D]
        patches = tokens.shape[1]
        tokens = torch.cat([self.global_tokens.expand(b, -1, -1), tokens.reshape(b, v * patches, -1)], dim=1)
        x = self.input_norm(tokens)  # [B, G + V*L, D]

        # Blocks [0, split) serve both heads; from split on, the physics head's global tokens come
        # from self.blocks and the Gaussian head's patch tokens from self.geometry_blocks.
        split = self.split
        taken: dict[int, Tensor] = {}
        g = self.cfg.num_global_tokens
        for i, block in enumerate(self.blocks):
            if i == split:
                geometry = x
            x = self._run(block, x)
            if i in self.cfg.out_layers and i < split:
                taken[i] = x[:, g:].reshape(b * v, patches, -1)
        for i, block in enumerate(self.geometry_blocks, start=split):
            geometry = self._run(block, geometry)
            if i in self.cfg.out_layers:
                taken[i] = geometry[:, g:].reshape(b * v, patches, -1)
        return BackboneOutput(x[:, :g], [taken[i] for i in self.cfg.out_layers], features)

    def _run(self, block: Block, x: Tensor) -> Tensor:
        if self.cfg.grad_checkpointing and self.training and torch.is_grad_enabled():
            return checkpoint(block, x, use_reentrant=False)
        return block(x)

    @property
    def split(self) -> int:
        """Index of the first block the Gaussian head has a copy of (``depth`` without copies)."""
        return self.cfg.depth - self.cfg.geometry_blocks

    def geometry_block_sources(self) -> dict[str, str]:
        """Each geometry-block weight's name -> the shared block weight it duplicates (names within
        the backbone): what a model without copies hands over to one with them."""
        return {
            f"geometry_blocks.{j}.{key}": f"blocks.{self.split + j}.{key}"
            for j, block in enumerate(self.geometry_blocks)
            for key in block.state_dict()
        }


def _blocks(cfg: BackboneConfig, count: int) -> list[Block]:
    return [
        Block(cfg.width, num_heads=cfg.width // cfg.head_dim, mlp_ratio=cfg.mlp_ratio) for _ in range(count)
    ]


def _init_linear(module: nn.Module) -> None:
    if isinstance(module, nn.Linear):
        nn.init.trunc_normal_(module.weight, std=0.02)
        if module.bias is not None:
            nn.init.zeros_(module.bias)
