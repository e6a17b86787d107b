"""``python -m physgm.train.evaluate``: test metrics of a checkpoint for 1 and 4 input views."""

import json
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from physgm.data.datamodule import PhysAssetsDataModule
from physgm.data.format import read_split
from physgm.train.evaluate import evaluate_views, main
from physgm.train.pretrain import LitPretrain, model_from_checkpoint, render_targets
from physgm.train.run import plain


def save_random_checkpoint(tmp_path: Path) -> Path:
    """An untrained 32 px model saved like Lightning saves it (hyper-parameters + state dict)."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(str(Path(__file__).resolve().parents[2] / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=["model.backbone.encoder.img_size=32"])
    torch.manual_seed(0)
    module = LitPretrain(model=plain(cfg.model), renderer={"backend": "warp", "num_threads": 1})
    path = tmp_path / "random.ckpt"
    torch.save({"hyper_parameters": dict(module.hparams), "state_dict": module.state_dict()}, path)
    return path


def test_evaluate_reports_both_view_counts_and_matches_a_hand_computation(tiny_dataset, tmp_path, capsys):
    ckpt = save_random_checkpoint(tmp_path)
    out = tmp_path / "metrics.json"
    assert main([str(ckpt), "--data", str(tiny_dataset), "--split", "train", "--num-targets", "5",
                 "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out)
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
    model = model_from_checkpoint(str(ckpt)).eval()
    dm = PhysAssetsDataModule(str(tiny_dataset), batch_size=3, eval_p_single=0.0, num_targets=5,
                              input_resolution=32, target_resolution=32, test_split="train")
    psnrs, psnrs_inputs, opacities = [], [], []
    with torch.no_grad():
        for batch in dm.test_dataloader():
            assert batch.images.shape[1] == 4
            out_ = model(batch.images, batch.masks, batch.c2w, batch.Ks)
            rgb, _ = render_targets(out_, batch.target_c2w, batch.target_Ks, 32, 32, {"backend": "torch"})
            rendered = rgb.permute(0, 1, 4, 2, 3).clamp(0, 1)
            mse = ((rendered - batch.target_images) ** 2).flatten(2).mean(-1)  # [B, 5]
            psnrs.append(-10 * torch.log10(mse[:, 4:]).flatten())
            psnrs_inputs.append(-10 * torch.log10(mse[:, :4]).flatten())
            opacities.append(out_.gaussians.opacities[out_.gaussians.valid])
    # different batching and renderer
    assert abs(float(torch.cat(psnrs).mean()) - report["views4"]["psnr"]) < 1e-3
    assert abs(float(torch.cat(psnrs_inputs).mean()) - report["views4"]["psnr_inputs"]) < 1e-3
    assert abs(float(torch.cat(opacities).median()) - report["views4"]["opacity_median"]) < 1e-5


def test_evaluate_single_view_batches_have_one_input(tiny_dataset, tmp_path):
    ckpt = save_random_checkpoint(tmp_path)
    model = model_from_checkpoint(str(ckpt)).eval()
    dm = PhysAssetsDataModule(str(tiny_dataset), batch_size=4, eval_p_single=1.0, num_targets=4,
                              input_resolution=32, target_resolution=32, test_split="train")
    seen = []
    original = model.forward

    def spy(images, *args, **kwargs):
        seen.append(images.shape[1])
        return original(images, *args, **kwargs)

    model.forward = spy
    r = evaluate_views(model, dm, {"backend": "warp", "num_threads": 1})
    assert set(seen) == {1} and r["assets"] == len(read_split(tiny_dataset, "train"))
