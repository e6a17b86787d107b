"""Image encoders: scratch ViT sizes, DINOv3 from a local file (round trip, Meta layout, errors)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import timm
import torch

from physgm.model import EncoderConfig, PhysGM
from physgm.model.encoder import build_encoder

DINO_S = EncoderConfig(
    kind="dinov3",
    arch="vit_small_patch16_dinov3",
    img_size=32,
    patch_size=16,
    embed_dim=384,
    depth=12,
    freeze=True,
)


@pytest.fixture(autouse=True)
def _no_downloads(monkeypatch):
    """Any attempt to fetch pretrained weights fails the test."""

    def refuse(*args, **kwargs):
        raise AssertionError("the model tried to download weights")

    monkeypatch.setattr(timm.models._builder, "load_pretrained", refuse)
    monkeypatch.setattr(timm.models._builder, "load_custom_pretrained", refuse)


@pytest.fixture(scope="module")
def dinov3_small_state():
    """A randomly initialised timm DINOv3 ViT-S/16 state dict (stands in for Meta's weights)."""
    torch.manual_seed(1)
    return timm.create_model("vit_small_patch16_dinov3", pretrained=False, num_classes=0).state_dict()


def test_scratch_vit_tokens_follow_config():
    enc = build_encoder(EncoderConfig(img_size=32, patch_size=8, embed_dim=48, depth=1, num_heads=2))
    tokens = enc(torch.rand(3, 3, 32, 48))
    assert tokens.shape == (3, 4 * 6, 48)  # any size that is a multiple of the patch
    with pytest.raises(ValueError, match="not a multiple of the encoder patch size 8"):
        enc(torch.rand(1, 3, 30, 32))


def test_dinov3_without_weights_explains_where_to_put_them(tmp_path):
    with pytest.raises(FileNotFoundError) as err:
        build_encoder(DINO_S)
    text = str(err.value)
    assert "model.backbone.encoder.weights" in text and "never downloaded" in text
    assert "vit_small_patch16_dinov3" in text
    missing = tmp_path / "nowhere" / "dinov3_vits16.pth"
    with pytest.raises(FileNotFoundError, match="does not exist") as err:
        build_encoder(replace(DINO_S, weights=str(missing)))
    assert str(missing) in str(err.value)
    with pytest.raises(ValueError, match="unknown DINOv3 architecture"):
        build_encoder(replace(DINO_S, arch="vit_tiny_patch3_dinov9"))


@pytest.mark.parametrize("suffix", [".pth", ".safetensors"])
def test_dinov3_local_round_trip(tmp_path, dinov3_small_state, suffix):
    path = tmp_path / f"dinov3_vits16{suffix}"
    if suffix == ".pth":
        torch.save(dinov3_small_state, path)
    else:
        from safetensors.torch import save_file

        save_file({k: v.contiguous() for k, v in dinov3_small_state.items()}, str(path))
    enc = build_encoder(replace(DINO_S, weights=str(path)))
    loaded = enc.vit.state_dict()
    assert loaded.keys() == dinov3_small_state.keys()
    for key, value in dinov3_small_state.items():
        assert torch.equal(loaded[key], value), key
    # Frozen as in the paper: no trainable parameters, eval mode even after .train().
    assert not any(p.requires_grad for p in enc.parameters())
    enc.train()
    assert not enc.vit.training
    tokens = enc(torch.rand(2, 3, 32, 48))
    assert tokens.shape == (2, 2 * 3, 384)  # cls + 4 register tokens dropped


def test_dinov3_meta_layout_is_converted(tmp_path, dinov3_small_state):
    """Meta's release names registers storage_tokens and layer scales ls1.gamma / ls2.gamma."""
    meta = {}
    for key, value in dinov3_small_state.items():
        key = (
            key.replace("reg_token", "storage_tokens")
            .replace("gamma_1", "ls1.gamma")
            .replace("gamma_2", "ls2.gamma")
        )
        meta[key] = value
    meta["mask_token"] = torch.zeros(1, 384)  # pretraining-only entry, dropped on load
    assert "storage_tokens" in meta and "blocks.0.ls1.gamma" in meta
    path = tmp_path / "dinov3_vits16_pretrain_lvd1689m.pth"
    torch.save(meta, path)
    enc = build_encoder(replace(DINO_S, weights=str(path)))
    assert torch.equal(enc.vit.reg_token, dinov3_small_state["reg_token"])
    assert torch.equal(enc.vit.blocks[3].gamma_2, dinov3_small_state["blocks.3.gamma_2"])


def test_dinov3_mismatch_is_a_clear_error(tmp_path, dinov3_small_state):
    broken = dict(dinov3_small_state)
    del broken["blocks.5.mlp.fc1.weight"]
    broken["head.extra.weight"] = torch.zeros(3)
    path = tmp_path / "broken.pth"
    torch.save(broken, path)
    with pytest.raises(RuntimeError, match="do not match the timm architecture") as err:
        build_encoder(replace(DINO_S, weights=str(path)))
    assert "blocks.5.mlp.fc1.weight" in str(err.value) and "head.extra.weight" in str(err.value)
    with pytest.raises(ValueError, match="patch_size=8"):
        torch.save(dinov3_small_state, path)
        build_encoder(replace(DINO_S, weights=str(path), patch_size=8))


def test_physgm_with_dinov3_encoder(tmp_path, dinov3_small_state, small_config, make_batch):
    path = tmp_path / "dinov3_vits16.pth"
    torch.save(dinov3_small_state, path)
    cfg = small_config()
    cfg.backbone.encoder = replace(DINO_S, weights=str(path))
    model = PhysGM(cfg).eval()
    batch = make_batch(1, 2, 32, 32)
    with torch.no_grad():
        out = model(batch["images"], batch["masks"], batch["c2w"], batch["Ks"])
    assert out.gaussians.means.shape == (1, 2 * 32 * 32, 3) and torch.isfinite(out.gaussians.means).all()
    encoder_params = {id(p) for p in model.backbone.encoder.parameters()}
    assert not any(p.requires_grad for p in model.parameters() if id(p) in encoder_params)
    # A checkpoint restores without the weights file (the encoder weights are in the state dict).
    path.unlink()
    from physgm.model import load_physgm

    clone = load_physgm(model.config.to_dict(), model.state_dict()).eval()
    with torch.no_grad():
        again = clone(batch["images"], batch["masks"], batch["c2w"], batch["Ks"])
    assert torch.equal(again.gaussians.means, out.gaussians.means)
