"""The material classifier on pooled encoder features, and its refit on a frozen stage-1 model."""

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
from physgm.train.refit_material import RefitConfig, draw_scenes, main, refit

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


def test_refit_refuses_a_vit_model_and_overwriting_its_input(data_root, tmp_path):
    save_checkpoint(
        PhysGM(PhysGMConfig.from_dict({"backbone": {"encoder": {"img_size": 32}}})), tmp_path / "vit.ckpt"
    )
    with pytest.raises(UserError, match="mobilenet_v2"):
        refit(tmp_path / "vit.ckpt", data_root, tmp_path / "out.ckpt", RefitConfig(epochs=1))
    with pytest.raises(SystemExit, match="overwrite"):
        main([str(tmp_path / "vit.ckpt"), "--data", str(data_root), "--out", str(tmp_path / "vit.ckpt")])
