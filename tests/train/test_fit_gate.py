"""The domain gate: its regression and ROC area by hand, its place in the material fusion, and
``fit_gate`` end to end on two tiny data sets that differ only in how their views look."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from physgm.cameras import orbit_cameras
from physgm.data.datamodule import PhysAssetsDataModule
from physgm.data.format import read_split
from physgm.errors import UserError
from physgm.model import PhysGM, PhysGMConfig
from physgm.model.checkpoint import load_model, save_checkpoint
from physgm.model.domain_gate import DomainGate
from physgm.model.physics_head import POOLED_DIM, fuse_material_logits, pooled_features
from physgm.train.fit_gate import GateConfig, fit_gate, fit_regression, main, roc_auc, split_views
from tests.train.test_refit_material import tiny_cnn_config


def test_roc_auc_counts_ties_half():
    # 3 x 2 pairs: 5 -> {1, 5} one above one tie; 7 -> above both; 0 -> below both
    assert roc_auc(torch.tensor([1.0, 5.0]), torch.tensor([5.0, 7.0, 0.0])) == pytest.approx(3.5 / 6)


def test_regression_separates_two_clouds_it_never_saw():
    gen = torch.Generator().manual_seed(0)
    shift = torch.zeros(POOLED_DIM)
    shift[:4] = 1.5  # the classes differ in four features out of POOLED_DIM
    synthetic = torch.randn(4000, POOLED_DIM, generator=gen)
    real = torch.randn(400, POOLED_DIM, generator=gen) + shift  # 10x fewer: the classes are balanced
    gate = DomainGate()
    gate.set_fit(*fit_regression(synthetic, real, GateConfig()))
    held_syn = torch.randn(500, POOLED_DIM, generator=gen)
    held_real = torch.randn(500, POOLED_DIM, generator=gen) + shift
    with torch.no_grad():
        p_syn, p_real = torch.sigmoid(gate.view_logits(held_syn)), torch.sigmoid(gate.view_logits(held_real))
    assert roc_auc(p_syn, p_real) > 0.94  # the Bayes classifier's is 0.98 (d' = 3), in 888 dimensions
    # balanced classes put the threshold midway: most of each class on its own side of 0.5
    assert (p_syn < 0.5).float().mean() > 0.75 and (p_real > 0.5).float().mean() > 0.75
    assert gate.weight[:4].min() > 3 * gate.weight[4:].abs().max()


def test_gate_is_the_mean_view_log_odds_of_a_standardised_regression():
    torch.manual_seed(0)
    model = PhysGM(tiny_cnn_config()).eval()
    images = torch.rand(2 * 3, 3, 32, 32)
    with torch.no_grad():
        feats = model.backbone.encoder.encode(images)  # 2 scenes x 3 views
    gate = DomainGate()
    shift, scale, weight = torch.randn(POOLED_DIM), torch.rand(POOLED_DIM) + 0.5, torch.randn(POOLED_DIM)
    gate.set_fit(shift, scale, weight, -0.3)
    per_view = pooled_features(feats, batch=6)  # [6, P]
    log_odds = ((per_view - shift) / scale @ weight - 0.3).reshape(2, 3).mean(1)
    torch.testing.assert_close(gate(feats, batch=2), torch.sigmoid(log_odds))
    with pytest.raises(ValueError, match="shape"):
        gate.set_fit(shift[:3], scale, weight, 0.0)


def test_the_gate_mixes_the_fused_and_the_heads_distributions_scene_by_scene():
    head = torch.randn(3, 15)
    log_prior = torch.randn(3, 15).log_softmax(-1)
    gate = torch.tensor([0.0, 0.3, 1.0])
    got = fuse_material_logits(head, log_prior, 8.0, 2.0, gate)
    p_head = head.softmax(-1)
    p_fused = p_head * log_prior.exp() ** 8.0
    p_fused = p_fused / p_fused.sum(-1, keepdim=True)
    for i, g in enumerate(gate.tolist()):
        mixture = g * p_fused[i] + (1 - g) * p_head[i]
        expected = (mixture.log() / 2.0).softmax(-1)
        torch.testing.assert_close(got[i].softmax(-1), expected, atol=1e-5, rtol=1e-4)
    # no gate: the product alone, as a model without one has always fused
    torch.testing.assert_close(fuse_material_logits(head, log_prior, 8.0).softmax(-1), p_fused)


def test_the_gate_mixes_in_the_procedural_expert_where_the_scene_looks_procedural():
    head, procedural = torch.randn(3, 15), torch.randn(3, 15)
    log_prior = torch.randn(3, 15).log_softmax(-1)
    gate = torch.tensor([0.0, 0.6, 1.0])
    p_head, p_procedural = head.softmax(-1), procedural.softmax(-1)
    p_fused = p_head * log_prior.exp() ** 4.0
    p_fused = p_fused / p_fused.sum(-1, keepdim=True)
    for weight, real in ((4.0, p_fused), (0.0, p_head)):  # at w = 0 the real expert is the head alone
        got = fuse_material_logits(head, log_prior, weight, 1.0, gate, procedural).softmax(-1)
        torch.testing.assert_close(got, gate[:, None] * real + (1 - gate[:, None]) * p_procedural)
    torch.testing.assert_close(got[0], p_procedural[0])  # g = 0: the procedural expert alone
    with pytest.raises(ValueError, match="pass gate"):
        fuse_material_logits(head, log_prior, 4.0, procedural_logits=procedural)


def test_model_with_a_gate_needs_the_cnn_encoder():
    with pytest.raises(ValueError, match="domain_gate.*mobilenet_v2"):
        PhysGM(PhysGMConfig.from_dict({"physics_head": {"domain_gate": True}}))


def _recoloured(src, dst):
    """A copy of a data set whose views show the same objects in inverted, speckled colours."""
    shutil.copytree(src, dst)
    rng = np.random.default_rng(0)
    for png in dst.glob("*/rgba/*.png"):
        rgba = np.asarray(Image.open(png)).copy()
        noise = rng.integers(0, 60, rgba.shape[:2] + (3,))
        rgba[..., :3] = np.clip(255 - rgba[..., :3].astype(int) + noise - 30, 0, 255).astype(np.uint8)
        Image.fromarray(rgba).save(png)
    shutil.rmtree(dst / "features", ignore_errors=True)
    return dst


def test_fit_gate_separates_the_two_sets_and_keeps_every_other_weight(tiny_dataset, tmp_path):
    synthetic = tmp_path / "synthetic"
    shutil.copytree(tiny_dataset, synthetic)  # the fit writes the feature caches into the data sets
    train = (synthetic / "splits" / "train.txt").read_text().split()
    (synthetic / "splits" / "val.txt").write_text("\n".join(train[:3]) + "\n")  # 10 assets leave val empty
    real = _recoloured(tiny_dataset, tmp_path / "real")
    torch.manual_seed(1)
    source = PhysGM(tiny_cnn_config())
    save_checkpoint(source, tmp_path / "s1.ckpt", global_step=3)
    out = tmp_path / "gated.ckpt"
    record = fit_gate(tmp_path / "s1.ckpt", synthetic, real, out, GateConfig(), held_out=real, log=print)
    model, ckpt = load_model(out)
    assert model.config.physics_head.domain_gate and model.config.physics_head.semantic_prior_weight == 1.5
    before, after = source.state_dict(), model.state_dict()
    assert {k for k in after if k not in before} == {
        f"domain_gate.{n}" for n in ("shift", "scale", "weight", "bias")
    }
    for k, v in before.items():
        assert torch.equal(v, after[k]), k
    assert (
        record["train"]["real"]["views1"]["p10"] > 0.9 and record["train"]["synthetic"]["views1"]["p90"] < 0.1
    )
    assert (
        record["real_test"]["view_auc"] > 0.99
    )  # the tiny set's splits overlap: a fit check, not a held-out one
    assert ckpt.raw["physgm"]["fit_gate"]["real"] == str(real)
    assert not (tmp_path / "gated.ckpt.tmp").exists()
    # the loaded model gates its prior with what the fit stored, scene by scene
    cams = orbit_cameras([0.0, 90.0], [0.0, 0.0], 1.8, 34.0, 32, 32)
    for root, high in ((real, True), (synthetic, False)):
        aid = read_split(root, "train")[0]
        feats = PhysAssetsDataModule(
            str(root), input_resolution=32, feature_cache="mobilenet_v2"
        ).feature_store()
        feats = feats.load(aid).map(lambda t: t[None, :2].float())  # [1, 2, ...] the first two cached views
        with torch.no_grad():
            got = model(
                torch.rand(1, 2, 3, 32, 32), torch.ones(1, 2, 1, 32, 32), cams.c2w[None], cams.Ks[None], feats
            )
            views = split_views([root], "train", 32)[0, :2]  # [2, P]
            expected = torch.sigmoid(model.domain_gate.view_logits(views).mean())[None]
        torch.testing.assert_close(got.domain_real, expected, atol=1e-5, rtol=0)
        assert float(expected) > 0.9 if high else float(expected) < 0.1
        fused = fuse_material_logits(got.head_material_logits, got.semantic_log_prior, 1.5, 1.0, expected)
        torch.testing.assert_close(got.physics.material_logits, fused)


def test_fit_gate_refuses_a_real_set_without_training_objects_and_overwriting(tiny_dataset, tmp_path):
    synthetic = tmp_path / "synthetic"
    shutil.copytree(tiny_dataset, synthetic)
    real = tmp_path / "real"
    shutil.copytree(tiny_dataset, real)
    (real / "splits" / "train.txt").write_text("")
    save_checkpoint(PhysGM(tiny_cnn_config()), tmp_path / "s1.ckpt")
    with pytest.raises(UserError, match="real_objects --set gate"):
        fit_gate(tmp_path / "s1.ckpt", synthetic, real, tmp_path / "out.ckpt", GateConfig())
    with pytest.raises(SystemExit, match="overwrite"):
        main(
            [
                str(tmp_path / "s1.ckpt"),
                "--data",
                str(synthetic),
                "--real",
                str(real),
                "--out",
                str(tmp_path / "s1.ckpt"),
            ]
        )
