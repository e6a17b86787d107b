"""``python -m physgm.train.export``: a slim checkpoint that predicts exactly what the training one does."""

import json
import math

import pytest
import torch

from physgm.cameras import orbit_cameras
from physgm.model.checkpoint import load_model
from physgm.train.export import main
from physgm.train.pretrain import LitPretrain

SMALL = {
    "backbone": {"encoder": {"img_size": 16, "depth": 1}, "depth": 4, "width": 64, "out_layers": [0, 1, 2, 3]}
}


def training_checkpoint(path):
    torch.manual_seed(0)
    module = LitPretrain(model=SMALL)
    opt = torch.optim.AdamW(module.parameters())
    sum(p.sum() for p in module.parameters()).backward()
    opt.step()  # real optimiser state (AdamW: 2 moments per weight), as a Lightning checkpoint holds it
    torch.save(
        {
            "hyper_parameters": dict(module.hparams),
            "state_dict": module.state_dict(),
            "global_step": 12,
            "optimizer_states": [opt.state_dict()],
            "loops": {"fit_loop": {}},
            "callbacks": {"x": 1},
        },
        path,
    )
    return module


def physics_of_both(module: LitPretrain, model) -> tuple:
    """The physics posteriors of the training module's model and of the exported one, on one random view."""
    cams = orbit_cameras([0], [0], 1.5, 40.0, 16, 16)
    images, masks = torch.rand(1, 1, 3, 16, 16), torch.ones(1, 1, 1, 16, 16)
    with torch.no_grad():
        before = module.model.eval()(images, masks, cams.c2w[None], cams.Ks[None]).physics
        after = model(images, masks, cams.c2w[None], cams.Ks[None]).physics
    return before, after


def test_export_keeps_predictions_and_drops_training_state(tmp_path, capsys):
    module = training_checkpoint(tmp_path / "train.ckpt")
    metrics = tmp_path / "m.json"
    metrics.write_text(json.dumps({"views4": {"psnr": 20.0}}))
    assert (
        main(
            [
                str(tmp_path / "train.ckpt"),
                str(tmp_path / "out" / "slim.ckpt"),
                "--recipe",
                "python train.py x=1",
                "--metrics",
                str(metrics),
            ]
        )
        == 0
    )
    report = json.loads(capsys.readouterr().out)
    slim = torch.load(tmp_path / "out" / "slim.ckpt", weights_only=False)
    assert set(slim) == {
        "hyper_parameters",
        "state_dict",
        "global_step",
        "epoch",
        "pytorch-lightning_version",
        "physgm",
    }
    assert (
        slim["physgm"]["recipe"] == "python train.py x=1"
        and slim["physgm"]["metrics"]["views4"]["psnr"] == 20.0
    )
    assert report["global_step"] == 12 and report["parameters"] == sum(
        p.numel() for p in module.model.parameters()
    )
    assert (tmp_path / "out" / "slim.ckpt").stat().st_size < 0.6 * (tmp_path / "train.ckpt").stat().st_size
    assert not list((tmp_path / "out").glob("*.tmp"))

    cams = orbit_cameras([0, 90, 180, 270], [0] * 4, 1.5, 40.0, 16, 16)
    images, masks = torch.rand(1, 4, 3, 16, 16), torch.ones(1, 4, 1, 16, 16)
    expected = module.model.eval()(images, masks, cams.c2w[None], cams.Ks[None])
    model, _ = load_model(tmp_path / "out" / "slim.ckpt")
    got = model(images, masks, cams.c2w[None], cams.Ks[None])
    assert torch.equal(got.gaussians.means, expected.gaussians.means)
    assert torch.equal(got.physics.material_logits, expected.physics.material_logits)


def test_export_refuses_a_file_that_is_not_a_training_checkpoint(tmp_path):
    torch.save({"state_dict": {}}, tmp_path / "x.ckpt")
    with pytest.raises(SystemExit, match="not a physgm checkpoint"):
        main([str(tmp_path / "x.ckpt"), str(tmp_path / "y.ckpt")])
    assert not (tmp_path / "y.ckpt").exists()


def test_export_sets_the_semantic_prior_weight(tmp_path, capsys):
    """The exported model multiplies the head's material distribution by the prior to the power w."""
    from physgm.model.semantic_prior import semantic_log_prior

    torch.manual_seed(0)
    mobilenet = {
        "backbone": {
            "encoder": {
                "kind": "mobilenet_v2",
                "patch_size": 16,
                "embed_dim": 448,
                "freeze": True,
                "img_size": 32,
            },
            "depth": 4,
            "width": 64,
            "out_layers": [0, 1, 2, 3],
        }
    }
    module = LitPretrain(model=mobilenet)
    torch.save(
        {"hyper_parameters": dict(module.hparams), "state_dict": module.state_dict()}, tmp_path / "t.ckpt"
    )
    assert main([str(tmp_path / "t.ckpt"), str(tmp_path / "w.ckpt"), "--prior-weight", "1.5"]) == 0
    model, _ = load_model(tmp_path / "w.ckpt")
    assert model.config.physics_head.semantic_prior_weight == 1.5
    cams = orbit_cameras([0], [0], 1.5, 40.0, 32, 32)
    images, masks = torch.rand(1, 1, 3, 32, 32), torch.ones(1, 1, 1, 32, 32)
    with torch.no_grad():
        head = module.model.eval()(images, masks, cams.c2w[None], cams.Ks[None]).physics.material_logits
        got = model(images, masks, cams.c2w[None], cams.Ks[None])
    expected = (head.log_softmax(-1) + 1.5 * got.semantic_log_prior).log_softmax(-1)  # normalised product
    torch.testing.assert_close(got.physics.material_logits, expected)
    logits = model.backbone.encoder.classify(images[0])
    torch.testing.assert_close(got.semantic_log_prior, semantic_log_prior(logits))
    # A classifier temperature T below 1 sharpens the ImageNet classes before they are folded.
    args = [str(tmp_path / "t.ckpt"), str(tmp_path / "wt.ckpt"), "--prior-weight", "1.5"]
    assert main([*args, "--prior-temperature", "0.5"]) == 0
    sharp, _ = load_model(tmp_path / "wt.ckpt")
    assert sharp.config.physics_head.semantic_prior_temperature == 0.5
    with torch.no_grad():
        got = sharp(images, masks, cams.c2w[None], cams.Ks[None])
    torch.testing.assert_close(got.semantic_log_prior, semantic_log_prior(logits / 0.5))
    assert not torch.allclose(got.semantic_log_prior, semantic_log_prior(logits))
    with pytest.raises(SystemExit, match="temperature must be > 0"):
        main([*args, "--prior-temperature", "0"])
    with pytest.raises(SystemExit, match="mobilenet_v2"):  # a ViT model has no ImageNet classes to read
        training_checkpoint(tmp_path / "vit.ckpt")
        main([str(tmp_path / "vit.ckpt"), str(tmp_path / "v.ckpt"), "--prior-weight", "1"])


def test_export_sets_the_calibration_offsets_of_the_log_variances(tmp_path):
    """The exported head adds the offsets to its log-variances and leaves the means alone."""
    module = training_checkpoint(tmp_path / "t.ckpt")
    assert main([str(tmp_path / "t.ckpt"), str(tmp_path / "c.ckpt"), "--logvar-offsets", "1.2", "-0.5"]) == 0
    model, _ = load_model(tmp_path / "c.ckpt")
    head = model.config.physics_head
    assert (head.E_logvar_offset, head.nu_logvar_offset) == (1.2, -0.5)
    before, after = physics_of_both(module, model)
    torch.testing.assert_close(after.z_E_logvar, before.z_E_logvar + 1.2)
    torch.testing.assert_close(after.z_nu_logvar, before.z_nu_logvar - 0.5)
    torch.testing.assert_close(after.z_E_mean, before.z_E_mean)
    torch.testing.assert_close(after.log10_E_std, before.log10_E_std * math.exp(0.6))


def test_export_sets_the_material_temperature(tmp_path):
    """The exported model divides its material logits by T: the same most likely material, softer."""
    module = training_checkpoint(tmp_path / "t.ckpt")
    assert main([str(tmp_path / "t.ckpt"), str(tmp_path / "c.ckpt"), "--material-temperature", "2.5"]) == 0
    model, _ = load_model(tmp_path / "c.ckpt")
    assert model.config.physics_head.material_temperature == 2.5
    before, after = physics_of_both(module, model)
    torch.testing.assert_close(after.material_logits, before.material_logits / 2.5)
    with pytest.raises(SystemExit, match="material-temperature must be > 0"):
        main([str(tmp_path / "t.ckpt"), str(tmp_path / "d.ckpt"), "--material-temperature", "0"])
