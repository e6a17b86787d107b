"""``python -m physgm.train.calibrate``: the E offset and material temperature that make the posterior's
90 % interval cover, chosen by the rule the module states."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from physgm.model import PhysGM, PhysGMConfig
from physgm.model.checkpoint import load_model, save_checkpoint
from physgm.model.posterior import PhysicsPosterior
from physgm.train import calibrate
from physgm.train.calibrate import ViewSet, choose_E_calibration
from physgm.train.evaluate import evaluate_views, view_datamodule
from physgm.train.export import main as export_main


def gaussian_set(z_true: torch.Tensor, E_ranges=None, material_logits=None) -> ViewSet:
    """Unit posteriors at z = 0, the true values at ``z_true`` (in material 0's frame)."""
    n = len(z_true)
    lo, hi = (3.0, 11.7) if E_ranges is None else (float(E_ranges[0, 0]), float(E_ranges[0, 1]))
    logits = torch.zeros(n, 2) if material_logits is None else material_logits
    post = PhysicsPosterior(logits, torch.zeros(n), torch.zeros(n), torch.zeros(n), torch.zeros(n), E_ranges)
    return ViewSet(4, post, lo + (z_true + 1) / 2 * (hi - lo), torch.full((n,), 0.25))


def test_global_frame_keeps_the_sharpest_offset_that_covers():
    # True z ~ N(0, 2^2) against a unit posterior: std x 2 (offset 2 ln 2 = 1.39) is the NLL optimum.
    # On the grid, offset 1.25 covers P(|N| < 1.645 e^0.625 / 2) = 0.875 and 1.5 covers 0.918.
    q = torch.linspace(0.0005, 0.9995, 2000, dtype=torch.float64)
    z_true = (2.0 * torch.special.ndtri(q)).float()
    best = choose_E_calibration([gaussian_set(z_true)])
    assert best["material_temperature"] == 1.0  # a global-frame E does not read the material
    assert best["E_offset_change"] == 1.5
    assert best["coverage"] == pytest.approx(0.918, abs=0.003)


def test_material_frame_widens_the_mixture_to_the_materials_it_doubts():
    # Two materials with E ranges 6 decades apart; the posterior gives material 1 a probability of
    # 0.018 (logit 4 against 0), but a quarter of the true values sit at the centre of material 1's
    # range, 14 of material 0's z units away. Widening each Gaussian (std x 4.5 at most) cannot reach
    # them; a temperature puts enough mass on material 1.
    ranges = torch.tensor([[3.0, 4.0], [10.0, 11.0]])
    n = 400
    logits = torch.tensor([[4.0, 0.0]]).expand(n, -1)
    q = torch.linspace(0.01, 0.99, 300)
    z_true = torch.cat([0.3 * torch.special.ndtri(q), torch.full((100,), 14.0)])  # 14: log10 E = 10.5
    data = gaussian_set(z_true, ranges, logits)
    assert float(((data.log10_E >= 10) & (data.log10_E <= 11)).float().mean()) == 0.25
    at_one = choose_E_calibration([data], temperatures=(1.0,))
    assert at_one["coverage"] < 0.9  # the best T = 1 pair misses the material-1 quarter
    best = choose_E_calibration([data])
    assert best["material_temperature"] > 1.0
    assert best["coverage"] >= 0.9
    cdf = calibrate.widened(
        data.posterior, best["material_temperature"], best["E_offset_change"]
    ).log10_E_cdf(data.log10_E)
    inside = (cdf >= 0.05) & (cdf <= 0.95)
    assert bool(inside[300:].all())  # now the material-1 values fall inside the mixture's interval


def tiny_material_frame_model() -> PhysGM:
    torch.manual_seed(3)
    config = PhysGMConfig.from_dict(
        {
            "backbone": {
                "encoder": {"img_size": 32, "depth": 1},
                "depth": 4,
                "width": 32,
                "head_dim": 16,
                "out_layers": [0, 1, 2, 3],
            },
            "gaussian_head": {"features": 8, "layer_channels": [8, 8, 16, 16], "hidden": 8},
            "physics_head": {"E_frame": "material", "nu_logvar_offset": 0.5},
        }
    )
    model = PhysGM(config)
    with torch.no_grad():  # a confident, wrong-half-the-time material head
        model.physics_head.material[-1].weight.normal_(std=0.5)
    return model.eval()


@pytest.fixture
def data_root(tiny_dataset, tmp_path):
    root = tmp_path / "data"
    shutil.copytree(tiny_dataset, root)
    train = (root / "splits" / "train.txt").read_text().split()
    (root / "splits" / "val.txt").write_text("\n".join(train) + "\n")
    return root


def test_cli_choice_exports_to_a_model_evaluate_scores_the_same(data_root, tmp_path, capsys):
    save_checkpoint(tiny_material_frame_model(), tmp_path / "m.ckpt", global_step=3)
    assert calibrate.main([str(tmp_path / "m.ckpt"), "--data", str(data_root)]) == 0
    record = json.loads(capsys.readouterr().out)
    n = len((data_root / "splits" / "val.txt").read_text().split())
    assert record["before"]["views4"]["assets"] == n and record["E_frame"] == "material"
    T, off_E, off_nu = record["material_temperature"], record["E_logvar_offset"], record["nu_logvar_offset"]
    assert f"--material-temperature {T:.4g}" in record["export"]
    export_main(
        [
            str(tmp_path / "m.ckpt"),
            str(tmp_path / "c.ckpt"),
            "--logvar-offsets",
            str(off_E),
            str(off_nu),
            "--material-temperature",
            str(T),
        ]
    )
    capsys.readouterr()  # export's own record
    model, _ = load_model(tmp_path / "c.ckpt")
    head = model.config.physics_head
    assert (head.material_temperature, head.E_logvar_offset, head.nu_logvar_offset) == (T, off_E, off_nu)
    for views in (1, 4):
        dm = view_datamodule(model, str(data_root), "val", views, 32, batch_size=8)
        scores = evaluate_views(model, dm, {"backend": "torch"})
        after = record["after"][f"views{views}"]
        assert scores["coverage90_E"] == pytest.approx(after["coverage_E"], abs=1e-6)
        assert scores["coverage90_nu"] == pytest.approx(after["coverage_nu"], abs=1e-6)
    # the calibrated file, measured again, covers what the calibration said it would
    assert calibrate.main([str(tmp_path / "c.ckpt"), "--data", str(data_root)]) == 0
    again = json.loads(capsys.readouterr().out)
    for key, after in record["after"].items():
        assert again["before"][key] == pytest.approx({**after, "assets": n})
    # T = 1 with no change is on the grid: the choice never covers less than the file did
    lowest = {w: min(r[v]["coverage_E"] for v in r) for w, r in record.items() if w in ("before", "after")}
    assert lowest["after"] >= lowest["before"]


def test_cli_errors(tmp_path):
    with pytest.raises(SystemExit, match="not found"):
        calibrate.main([str(tmp_path / "none.ckpt"), "--data", str(tmp_path)])
    save_checkpoint(tiny_material_frame_model(), tmp_path / "m.ckpt")
    with pytest.raises(SystemExit, match="--level must be between 0 and 1"):
        calibrate.main([str(tmp_path / "m.ckpt"), "--data", str(tmp_path), "--level", "90"])
    with pytest.raises(SystemExit, match="mobilenet_v2"):  # a ViT model has no semantic prior to weigh
        calibrate.main([str(tmp_path / "m.ckpt"), "--data", str(tmp_path), "--prior-weight", "2"])
