"""physgm's transformer block against timm's ViT block, whose parameter names the checkpoints use."""

from __future__ import annotations

import pytest
import torch
from timm.models.vision_transformer import Block as TimmBlock

from physgm.model.transformer import Block


def test_block_equals_timm_s_with_the_same_weights():
    torch.manual_seed(0)
    ref = TimmBlock(96, num_heads=4, mlp_ratio=2.0, qkv_bias=True).eval()
    for p in ref.parameters():  # away from LayerNorm's ones and zeros, so every parameter counts
        p.data.normal_(0.0, 0.2)
    ours = Block(96, num_heads=4, mlp_ratio=2.0).eval()
    ours.load_state_dict(ref.state_dict(), strict=True)
    x = torch.randn(2, 37, 96)
    with torch.no_grad():
        torch.testing.assert_close(ours(x), ref(x), rtol=1e-5, atol=1e-5)


def test_width_must_split_into_heads():
    with pytest.raises(ValueError, match="divisible"):
        Block(96, num_heads=5)
