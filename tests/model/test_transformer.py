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


def test_a_block_on_its_first_tokens_equals_the_whole_block_cut_there():
    torch.manual_seed(0)
    block = Block(64, num_heads=2)
    for p in block.parameters():
        p.data.normal_(0.0, 0.2)
    x = torch.randn(2, 21, 64, requires_grad=True)
    whole = block(x)
    cut = block(x, queries=3)
    assert cut.shape == (2, 3, 64)
    torch.testing.assert_close(cut, whole[:, :3], rtol=1e-5, atol=1e-5)
    # the gradients of what the first tokens feed are the same too
    weights = torch.randn(2, 3, 64)
    grads_whole = torch.autograd.grad((whole[:, :3] * weights).sum(), [x, *block.parameters()])
    grads_cut = torch.autograd.grad((cut * weights).sum(), [x, *block.parameters()])
    for a, b in zip(grads_cut, grads_whole, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
