"""Refits on a frozen stage-1 model: the material classifier on pooled encoder features, and the E
regression relative to the material's range (``refit_stiffness``)."""

from __future__ import annotations

import shutil

import pytest
import torch

from physgm.cameras import orbit_cameras
from physgm.data.format import load_asset, read_split
from physgm.errors import UserError
from physgm.model import PhysGM, PhysGMConfig
from physgm.model.checkpoint import load_model, save_checkpoint
from physgm.model.physics_head import POOLED_DIM, pooled_features
from physgm.model.posterior import material_E_ranges
from physgm.train import refit_stiffness
from physgm.train.refit_material import RefitConfig, draw_scenes, main, refit
from physgm.train.refit_stiffness import StiffnessRefitConfig, TokenSplit, fit, posterior_mean_errors

MOBILENET = {"kind": "mobilenet_v2", "patch_size": 16, "embed_dim": 448, "freeze": True, "img_size": 32}


def tiny_cnn_config(material_input: str = "token") -> PhysGMConfig:
    return PhysGMConfig.from_dict(
        {
            "backbone": {
                "encoder": MOBILENET,
                **{"width": 32, "depth": 4, "head_dim": 16, "camera_dim": 8, "camera_hidden": 16},
                "out_layers": (0, 1, 2, 3),
            },
            "gaussian_head": {"features": 8, "layer_channels": (8, 8, 16, 16), "hidden": 8},
            "physics_head": {
                "material_input": material_input,
                "feature_hidden": 16,
                "semantic_prior_weight": 1.5,
                "E_logvar_offset": 0.25,
            },
        }
    )


def test_forward_reads_the_material_from_the_pooled_views():
    torch.manual_seed(0)
    model = PhysGM(tiny_cnn_config("features")).eval()
    with torch.no_grad():
        model.physics_head.material.out.bias.normal_()  # logits that differ between materials
    cams = orbit_cameras([0.0, 90.0], [0.0, 0.0], 1.8, 34.0, 32, 32)
    images = torch.rand(2, 2, 3, 32, 32)
    with torch.no_grad():
        c2w, Ks = cams.c2w.expand(2, -1, -1, -1), cams.Ks.expand(2, -1, -1, -1)
        out = model(images, torch.ones(2, 2, 1, 32, 32), c2w, Ks)
        feats = model.backbone.encoder.encode(images.flatten(0, 1))  # [B * V, ...]
        pooled = pooled_features(feats, batch=2)
        # pooling averages over the views: the same as pooling each view and averaging
        per_view = pooled_features(feats, batch=4).reshape(2, 2, POOLED_DIM).mean(1)
    torch.testing.assert_close(pooled, per_view)
    torch.testing.assert_close(out.head_material_logits, model.physics_head.material(pooled))


def test_features_input_needs_the_cnn_encoder_and_a_known_name():
    with pytest.raises(ValueError, match="mobilenet_v2"):
        PhysGM(PhysGMConfig.from_dict({"physics_head": {"material_input": "features"}}))
    with pytest.raises(ValueError, match="material_input must be one of"):
        PhysGM(tiny_cnn_config("pixels"))


def test_drawn_scenes_are_one_view_or_four_distinct_views_averaged():
    # view j of asset a is the vector 10**j: a mean of 4 distinct views has 4 digits of 0.25
    views = torch.tensor([[10.0**j for j in range(6)]]).T[None].expand(50, -1, -1).clone()  # [50, 6, 1]
    drawn = draw_scenes(views, p_single=0.5, gen=torch.Generator().manual_seed(0))[:, 0]
    singles = [x for x in drawn.tolist() if x in {10.0**j for j in range(6)}]
    fours = [x for x in drawn.tolist() if x not in singles]
    assert 10 < len(singles) < 40 and len(singles) + len(fours) == 50
    for x in fours:
        digits = [int(d) for d in f"{round(4 * x):06d}"]
        assert sorted(digits) == [0, 0, 1, 1, 1, 1]  # 4 distinct views, each once


@pytest.fixture
def data_root(tiny_dataset, tmp_path):
    root = tmp_path / "data"
    shutil.copytree(tiny_dataset, root)  # the refit writes the feature cache into the data set
    train = (root / "splits" / "train.txt").read_text().split()
    (root / "splits" / "val.txt").write_text("\n".join(train[:3]) + "\n")  # 10 assets leave val empty
    return root


def test_refit_fits_the_annotations_and_keeps_every_other_weight(data_root, tmp_path):
    torch.manual_seed(1)
    source = PhysGM(tiny_cnn_config("token"))
    save_checkpoint(source, tmp_path / "s1.ckpt", global_step=7)
    out = tmp_path / "refit.ckpt"
    record = refit(tmp_path / "s1.ckpt", data_root, out, RefitConfig(epochs=40), log=print)
    model, ckpt = load_model(tmp_path / "refit.ckpt")
    head = model.config.physics_head
    assert (head.material_input, head.semantic_prior_weight, head.E_logvar_offset) == ("features", 1.5, 0.25)
    before, after = source.state_dict(), model.state_dict()
    for k, v in before.items():
        if not k.startswith("physics_head.material."):
            assert torch.equal(v, after[k]), k
    labels = [load_asset(data_root / a).physical.annotation.material for a in read_split(data_root, "train")]
    majority = max(labels.count(m) for m in labels) / len(labels)
    assert majority < 0.35  # so fitting the annotations means reading the views
    assert record["train_accuracy_annotated"]["views1"] >= 0.7
    assert ckpt.raw["physgm"]["refit_material"]["best"]["epoch"] >= 1
    assert not (tmp_path / "refit.ckpt.tmp").exists()


def test_procedural_expert_refit_keeps_the_token_classifier_and_the_gate_mixes_them(data_root, tmp_path):
    torch.manual_seed(2)
    config = tiny_cnn_config("token")
    config.physics_head.domain_gate = True
    source = PhysGM(config)
    gen = torch.Generator().manual_seed(3)
    source.domain_gate.set_fit(
        torch.randn(POOLED_DIM, generator=gen),
        torch.rand(POOLED_DIM, generator=gen) + 0.5,
        torch.randn(POOLED_DIM, generator=gen) * 0.005,
        0.2,
    )
    save_checkpoint(source, tmp_path / "gated.ckpt", global_step=5)
    out = tmp_path / "experts.ckpt"
    argv = [str(tmp_path / "gated.ckpt"), "--data", str(data_root), "--out", str(out), "--epochs", "40"]
    assert main([*argv, "--procedural-expert"]) == 0
    model, ckpt = load_model(out)
    head = model.config.physics_head
    assert (head.material_input, head.procedural_expert, head.domain_gate) == ("token", True, True)
    before, after = source.state_dict(), model.state_dict()
    assert {k for k in after if k not in before} == {
        k for k in after if k.startswith("physics_head.procedural.")
    }
    for k, v in before.items():  # the token classifier and the gate among them
        assert torch.equal(v, after[k]), k
    record = ckpt.raw["physgm"]["refit_material"]
    assert record["train_accuracy_annotated"]["views1"] >= 0.7
    assert record["config"]["procedural_expert"] and ckpt.raw["physgm"]["recipe"].endswith(
        "--procedural-expert"
    )
    # the output: g * norm(p_token * p_prior^w) + (1 - g) * p_procedural, with the expert's own logits
    cams = orbit_cameras([0.0, 90.0], [0.0, 0.0], 1.8, 34.0, 32, 32)
    images = torch.rand(3, 2, 3, 32, 32)
    with torch.no_grad():
        c2w, Ks = cams.c2w.expand(3, -1, -1, -1), cams.Ks.expand(3, -1, -1, -1)
        got = model(images, torch.ones(3, 2, 1, 32, 32), c2w, Ks)
        feats = model.backbone.encoder.encode(images.flatten(0, 1))
        procedural = model.physics_head.procedural(pooled_features(feats, batch=3))
        g = model.domain_gate(feats, batch=3)[:, None]
    torch.testing.assert_close(got.procedural_material_logits, procedural)
    real = got.head_material_logits.softmax(-1) * got.semantic_log_prior.exp() ** 1.5
    mixture = g * real / real.sum(-1, keepdim=True) + (1 - g) * procedural.softmax(-1)
    torch.testing.assert_close(got.physics.material_logits.softmax(-1), mixture, atol=1e-5, rtol=1e-4)
    assert 0.05 < float(g.min()) and float(g.max()) < 0.95  # both experts count in these scenes


def test_procedural_expert_needs_a_gate_and_a_token_classifier(data_root, tmp_path):
    config = tiny_cnn_config("token")
    config.physics_head.procedural_expert = True
    with pytest.raises(ValueError, match="needs physics_head.domain_gate"):
        PhysGM(config)
    config.physics_head.domain_gate, config.physics_head.material_input = True, "features"
    with pytest.raises(ValueError, match="use one or the other"):
        PhysGM(config)
    save_checkpoint(PhysGM(tiny_cnn_config("token")), tmp_path / "ungated.ckpt")
    with pytest.raises(UserError, match="fit the gate first"):
        refit(
            tmp_path / "ungated.ckpt",
            data_root,
            tmp_path / "out.ckpt",
            RefitConfig(epochs=1, procedural_expert=True),
        )
    assert not (tmp_path / "out.ckpt").exists()


def test_refit_refuses_a_vit_model_and_overwriting_its_input(data_root, tmp_path):
    save_checkpoint(
        PhysGM(PhysGMConfig.from_dict({"backbone": {"encoder": {"img_size": 32}}})), tmp_path / "vit.ckpt"
    )
    with pytest.raises(UserError, match="mobilenet_v2"):
        refit(tmp_path / "vit.ckpt", data_root, tmp_path / "out.ckpt", RefitConfig(epochs=1))
    with pytest.raises(SystemExit, match="overwrite"):
        main([str(tmp_path / "vit.ckpt"), "--data", str(data_root), "--out", str(tmp_path / "vit.ckpt")])


def test_refit_fits_E_in_the_material_frame_and_keeps_every_other_weight(data_root, tmp_path):
    torch.manual_seed(1)
    source = PhysGM(tiny_cnn_config("token"))
    save_checkpoint(source, tmp_path / "s1.ckpt", global_step=7)
    out = tmp_path / "stiff.ckpt"
    cfg = StiffnessRefitConfig(epochs=200, lr=3e-3)
    record = refit_stiffness.refit(tmp_path / "s1.ckpt", data_root, out, cfg, log=print)
    model, ckpt = load_model(out)
    head = model.config.physics_head
    assert (head.E_frame, head.E_logvar_offset, head.semantic_prior_weight) == ("material", 0.0, 1.5)
    before, after = source.state_dict(), model.state_dict()
    assert any(not torch.equal(before[k], after[k]) for k in after if k.startswith("physics_head.young."))
    for k, v in before.items():
        if not k.startswith("physics_head.young."):
            assert torch.equal(v, after[k]), k
    assert ckpt.raw["physgm"]["refit_stiffness"]["best"]["epoch"] == record["best"]["epoch"] >= 10
    assert not (tmp_path / "stiff.ckpt.tmp").exists()
    # The saved model reads E in the frame of its most likely material in a full forward pass.
    cams = orbit_cameras([0.0, 90.0], [0.0, 0.0], 1.8, 34.0, 32, 32)
    with torch.no_grad():
        post = model(
            torch.rand(1, 2, 3, 32, 32), torch.ones(1, 2, 1, 32, 32), cams.c2w[None], cams.Ks[None]
        ).physics
    lo, hi = material_E_ranges()[post.material_logits.argmax(-1)].unbind(-1)
    torch.testing.assert_close(post.log10_E_mean, lo + (post.z_E_mean + 1) / 2 * (hi - lo))


def test_stiffness_refit_refuses_overwriting_its_input_and_too_few_epochs(tmp_path):
    save_checkpoint(PhysGM(tiny_cnn_config("token")), tmp_path / "s1.ckpt")
    base = [str(tmp_path / "s1.ckpt"), "--data", str(tmp_path)]
    with pytest.raises(SystemExit, match="overwrite"):
        refit_stiffness.main([*base, "--out", str(tmp_path / "s1.ckpt")])
    with pytest.raises(SystemExit, match="at least 10"):
        refit_stiffness.main([*base, "--out", str(tmp_path / "o.ckpt"), "--epochs", "3"])
    with pytest.raises(SystemExit, match="not found"):
        refit_stiffness.main(
            [str(tmp_path / "none.ckpt"), "--data", str(tmp_path), "--out", str(tmp_path / "o.ckpt")]
        )


def token_set(n: int, seed: int) -> TokenSplit:
    """Tokens whose first channel carries the position of E in its material's range, as a cue would."""
    gen = torch.Generator().manual_seed(seed)
    material = torch.randint(0, 15, (n,), generator=gen)
    z = torch.rand(n, generator=gen) * 2 - 1
    lo, hi = material_E_ranges()[material].unbind(-1)
    tokens = torch.randn(n, 16, generator=gen)
    tokens[:, 0] = 3 * z
    logits = torch.nn.functional.one_hot(material, 15).float()
    return TokenSplit(tokens, logits, material, lo + (z + 1) / 2 * (hi - lo), torch.full((n,), 4))


def test_stiffness_fit_reads_the_cue_in_each_materials_frame():
    from physgm.model.config import PhysicsHeadConfig
    from physgm.model.physics_head import PhysicsHead

    torch.manual_seed(0)
    head = PhysicsHead(PhysicsHeadConfig(E_frame="material"), dim=16, num_global_tokens=3)
    train, val = token_set(400, 0), token_set(100, 1)
    best = fit(head, train, val, StiffnessRefitConfig(epochs=60, lr=3e-3), log=lambda *_: None)
    fitted = float(posterior_mean_errors(head, val).median())
    centre = float(posterior_mean_errors(head, val, centre=True).median())
    assert fitted < 0.3 * centre and best["val_views4"] == pytest.approx(fitted)


def test_refits_pool_the_train_and_val_splits_of_several_roots(data_root, tmp_path):
    second = tmp_path / "second"
    shutil.copytree(data_root, second)
    ids = read_split(second, "train")
    (second / "splits" / "train.txt").write_text("\n".join(ids[:4]) + "\n")
    (second / "splits" / "val.txt").write_text("")  # a root without a val split adds none
    save_checkpoint(PhysGM(tiny_cnn_config("token")), tmp_path / "s1.ckpt")
    one = refit(tmp_path / "s1.ckpt", data_root, tmp_path / "one.ckpt", RefitConfig(epochs=2))
    both = refit(tmp_path / "s1.ckpt", [data_root, second], tmp_path / "both.ckpt", RefitConfig(epochs=2))
    assert both["assets"] == {"train": one["assets"]["train"] + 4, "val": one["assets"]["val"]}
    assert both["data"] == [str(data_root), str(second)]
    _, ckpt = load_model(tmp_path / "both.ckpt")
    assert f"--data {data_root} {second} " in ckpt.raw["physgm"]["recipe"]
    train = refit_stiffness.token_splits(
        load_model(tmp_path / "s1.ckpt")[0].eval(), [data_root, second], "train", 32
    )
    assert len(train.tokens) == 2 * (one["assets"]["train"] + 4)  # every asset with 4 views and with 1
    (second / "splits" / "train.txt").write_text("")
    with pytest.raises(UserError, match="no 'train' assets to refit on in .*second"):
        refit(tmp_path / "s1.ckpt", [second], tmp_path / "none.ckpt", RefitConfig(epochs=1))
