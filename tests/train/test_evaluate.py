"""``python -m physgm.train.evaluate``: test metrics of a checkpoint for 1 and 4 input views."""

import json
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from physgm.data.datamodule import PhysAssetsDataModule
from physgm.data.format import read_split
from physgm.metrics.lpips import load_lpips
from physgm.model.checkpoint import load_model
from physgm.train.evaluate import evaluate_views, main
from physgm.train.pretrain import LitPretrain, render_targets
from physgm.train.run import plain


def save_random_checkpoint(tmp_path: Path, model: str = "physgm") -> Path:
    """An untrained 32 px model saved like Lightning saves it (hyper-parameters + state dict)."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(str(Path(__file__).resolve().parents[2] / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=[f"model={model}", "model.backbone.encoder.img_size=32"])
    torch.manual_seed(0)
    module = LitPretrain(model=plain(cfg.model), renderer={"backend": "warp", "num_threads": 1})
    path = tmp_path / f"random_{model}.ckpt"
    torch.save({"hyper_parameters": dict(module.hparams), "state_dict": module.state_dict()}, path)
    return path


def test_evaluate_reports_both_view_counts_and_matches_a_hand_computation(tiny_dataset, tmp_path, capsys):
    ckpt = save_random_checkpoint(tmp_path)
    out = tmp_path / "metrics.json"
    assert (
        main(
            [
                str(ckpt),
                "--data",
                str(tiny_dataset),
                "--split",
                "train",
                "--num-targets",
                "5",
                "--lpips-net",
                "mobilenet",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    report = json.loads(capsys.readouterr().out)
    assert report["lpips_net"] == "mobilenet"
    assert json.loads(out.read_text()) == report
    n = len(read_split(tiny_dataset, "train"))
    for key in ("views1", "views4"):
        r = report[key]
        assert r["assets"] == n
        matrix = torch.tensor(r["confusion"]["matrix"])
        assert int(matrix.sum()) == n
        assert abs(r["material_acc"] - float(matrix.trace()) / n) < 1e-6
        assert 0 <= r["coverage90_E"] <= 1 and r["ssim"] <= 1

    # PSNR by hand over the novel views of the 4-view inputs: mean over images of -10 log10(MSE).
    model, _ = load_model(ckpt)
    dm = PhysAssetsDataModule(
        str(tiny_dataset),
        batch_size=3,
        eval_p_single=0.0,
        num_targets=5,
        input_resolution=32,
        target_resolution=32,
        test_split="train",
    )
    psnrs, psnrs_inputs, opacities, perceptual, novel_mse = [], [], [], [], []
    feature_distance = load_lpips("mobilenet")
    outside_error, all_error, outside_alpha = [], [], []
    with torch.no_grad():
        for batch in dm.test_dataloader():
            assert batch.images.shape[1] == 4
            out_ = model(batch.images, batch.masks, batch.c2w, batch.Ks)
            rgb, alpha = render_targets(out_, batch.target_c2w, batch.target_Ks, 32, 32, {"backend": "torch"})
            rendered = rgb.permute(0, 1, 4, 2, 3).clamp(0, 1)
            mse = ((rendered - batch.target_images) ** 2).flatten(2).mean(-1)  # [B, 5]
            error = ((rendered - batch.target_images) ** 2).mean(2)[:, 4:]  # [B, 1, H, W] novel view
            outside = batch.target_masks[:, 4:, 0] <= 0.5
            outside_error.append(error[outside])
            all_error.append(error.flatten())
            outside_alpha.append(alpha[:, 4:, ..., 0][outside])
            psnrs.append(-10 * torch.log10(mse[:, 4:]).flatten())
            novel_mse.append(mse[:, 4:].flatten())
            psnrs_inputs.append(-10 * torch.log10(mse[:, :4]).flatten())
            opacities.append(out_.gaussians.opacities[out_.gaussians.valid])
            perceptual.append(
                feature_distance(
                    rendered[:, 4:].flatten(0, 1), batch.target_images[:, 4:].flatten(0, 1), normalize=True
                )
            )
    # different batching and renderer
    assert abs(float(torch.cat(psnrs).mean()) - report["views4"]["psnr"]) < 1e-3
    assert abs(float(torch.cat(psnrs_inputs).mean()) - report["views4"]["psnr_inputs"]) < 1e-3
    assert abs(float(torch.cat(opacities).median()) - report["views4"]["opacity_median"]) < 1e-5
    assert abs(float(torch.cat(perceptual).mean()) - report["views4"]["lpips"]) < 1e-3
    share = float(torch.cat(outside_error).sum() / torch.cat(all_error).sum())
    assert 0 < share < 1 and abs(share - report["views4"]["error_outside_mask"]) < 1e-3
    assert abs(float(torch.cat(outside_alpha).mean()) - report["views4"]["alpha_outside_mask"]) < 1e-3
    # the angle bins hold every novel view once, and pooled back together give the views' mean MSE
    bins = report["views4"]["psnr_by_angle"].values()
    assert sum(b["views"] for b in bins) == n
    pooled = sum(b["views"] * 10 ** (-b["psnr"] / 10) for b in bins) / n
    assert abs(pooled / float(torch.cat(novel_mse).mean()) - 1) < 1e-3


def test_evaluate_single_view_batches_have_one_input(tiny_dataset, tmp_path):
    ckpt = save_random_checkpoint(tmp_path)
    model, _ = load_model(ckpt)
    dm = PhysAssetsDataModule(
        str(tiny_dataset),
        batch_size=4,
        eval_p_single=1.0,
        num_targets=4,
        input_resolution=32,
        target_resolution=32,
        test_split="train",
    )
    seen = []
    original = model.forward

    def spy(images, *args, **kwargs):
        seen.append(images.shape[1])
        return original(images, *args, **kwargs)

    model.forward = spy
    r = evaluate_views(model, dm, {"backend": "warp", "num_threads": 1})
    assert set(seen) == {1} and r["assets"] == len(read_split(tiny_dataset, "train"))


def test_evaluate_scores_labelled_real_assets_and_sweeps_the_prior(tiny_dataset, tmp_path, capsys):
    """Assets without true physics (no annotation: real objects) are scored against their label."""
    import shutil

    from physgm.data.format import load_asset
    from physgm.physics.behaviour import behaviour_index
    from physgm.physics.materials import MATERIAL_NAMES
    from physgm.train.evaluate import fused_logits

    root = tmp_path / "real"
    shutil.copytree(tiny_dataset, root)
    for phys in root.glob("*/physical.json"):
        data = json.loads(phys.read_text())
        data.pop("annotation")  # what a hand-labelled real asset looks like
        phys.write_text(json.dumps(data))
    ckpt = save_random_checkpoint(tmp_path, model="physgm_mobilenet")
    args = ["--data", str(root), "--split", "train", "--views", "1", "--num-targets", "4"]
    args += ["--prior-sweep", "0,2"]
    assert main([str(ckpt), *args]) == 0
    r = json.loads(capsys.readouterr().out)["views1"]
    ids = read_split(root, "train")
    assert r["labelled_assets"] == len(ids) and "material_acc" not in r  # no true physics to score
    matrix = torch.tensor(r["label_confusion"]["matrix"])
    assert abs(r["label_material_acc"] - float(matrix.trace()) / len(ids)) < 1e-6
    assert r["prior_sweep"]["0.0"]["label_material_acc"] == r["label_material_acc"]  # the checkpoint's w is 0
    # By hand at w = 2: argmax of log p_head + 2 log p_prior, against each asset's labelled material.
    model, _ = load_model(ckpt)
    dm = PhysAssetsDataModule(
        str(root),
        batch_size=4,
        eval_p_single=1.0,
        num_targets=4,
        input_resolution=32,
        target_resolution=32,
        test_split="train",
    )
    beh = behaviour_index()
    hits, beh_hits, head_top, prior_top = [], [], [], []
    with torch.no_grad():
        for batch in dm.test_dataloader():
            out = model(batch.images, batch.masks, batch.c2w, batch.Ks)
            pred = fused_logits(out, 2.0).argmax(-1)
            head_top.append(out.head_material_logits.softmax(-1).max(-1).values)
            prior_top.append(out.semantic_log_prior.exp().max(-1).values)
            labels = torch.tensor(
                [MATERIAL_NAMES.index(load_asset(root / a).physical.material) for a in batch.asset_ids]
            )
            hits.append(pred == labels)
            beh_hits.append(beh[pred] == beh[labels])
    assert abs(float(torch.cat(hits).float().mean()) - r["prior_sweep"]["2.0"]["label_material_acc"]) < 1e-6
    assert (
        abs(float(torch.cat(beh_hits).float().mean()) - r["prior_sweep"]["2.0"]["label_behaviour_acc"]) < 1e-6
    )
    assert 0.0 <= r["prior_only_material_acc"] <= r["prior_only_behaviour_acc"] <= 1.0
    # How sure each source is: percentiles of the most probable material's probability.
    for source, tops in (("head", head_top), ("prior", prior_top)):
        tops = torch.cat(tops)
        got = r["confidence"][source]
        # evaluate reads the encoder's features from the cache (stored at lower precision)
        assert abs(got["p50"] - float(tops.quantile(0.5))) < 2e-3
        assert 1 / len(MATERIAL_NAMES) - 1e-6 <= got["p10"] <= got["p50"] <= got["p90"]
        assert got["p90"] <= float(tops.max()) + 2e-3

    # --max-assets: the same split scored on its first and middle assets only.
    assert main([str(ckpt), *args, "--max-assets", "2"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["max_assets"] == 2 and report["views1"]["labelled_assets"] == 2
    with pytest.raises(SystemExit, match="--max-assets must be at least 1"):
        main([str(ckpt), *args, "--max-assets", "0"])
