"""The volume benchmark: the body simulate fills Gaussians with, against the asset's own."""

from __future__ import annotations

import json
import math
import shutil

import pytest
import torch

from physgm.bench import volume
from physgm.bench.e2e import random_checkpoint
from physgm.errors import UserError
from physgm.gaussians import Gaussians


def _sphere(n: int, radius: float, opacity: float) -> Gaussians:
    g = torch.Generator().manual_seed(0)
    means = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * radius
    return Gaussians(
        means=means,
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        scales=torch.full((n, 3), 0.01),
        opacities=torch.full((n,), opacity),
        colors=torch.rand(n, 3, generator=g),
    )


def test_enclosed_volume_of_a_shell_is_the_ball_it_bounds():
    ball = _sphere(20_000, 0.5, 0.9)
    volume_m3 = volume.enclosed_volume(ball, 1.0 / 24, 0.05)  # the planner's spacing for a unit object
    assert volume_m3 == pytest.approx(4 / 3 * math.pi * 0.5**3, rel=0.1)
    assert volume.enclosed_volume(_sphere(100, 0.5, 0.01), 0.05, 0.05) == 0.0  # nothing that opaque


def test_report_compares_each_threshold_on_the_same_assets(tiny_dataset, tmp_path, capsys):
    ckpt = random_checkpoint(tmp_path)
    args = ["--data", str(tiny_dataset), "--split", "train", "--assets", "3", "--min-opacity", "0.05", "0.0"]
    report = volume.main([str(ckpt), *args])
    assert json.loads(capsys.readouterr().out) == report
    assert report["assets"] == 3 and set(report["thresholds"]) == {"0.05", "0.0", "planner"}
    counts = {t: r["opaque"]["assets"] + r["translucent"]["assets"] for t, r in report["thresholds"].items()}
    assert counts == {"0.05": 3, "0.0": 3, "planner": 3}
    everything, planner = report["thresholds"]["0.0"], report["thresholds"]["planner"]
    # With every Gaussian kept the body can only grow; the planner's threshold lies in between.
    for part in ("opaque", "translucent"):
        if everything[part]["assets"]:
            assert everything[part]["median"] >= planner[part]["median"]
            assert planner[part]["median"] >= report["thresholds"]["0.05"][part]["median"]


def test_bad_input_is_a_clear_error(tmp_path):
    with pytest.raises(UserError, match="not found"):
        volume.main([str(tmp_path / "none.ckpt"), "--data", str(tmp_path)])
    ckpt = tmp_path / "x.ckpt"
    ckpt.write_bytes(b"")
    with pytest.raises(UserError, match="physgm.data.synth"):
        volume.main([str(ckpt), "--data", str(tmp_path)])


def test_an_asset_without_its_own_gaussians_is_a_clear_error(tiny_dataset, tmp_path):
    # A real-object set has renders and labels but no gaussians.ply to compare with.
    root = tmp_path / "copy"
    shutil.copytree(tiny_dataset, root)
    first = (root / "splits" / "train.txt").read_text().split()[0]
    (root / first / "gaussians.ply").unlink()
    ckpt = random_checkpoint(tmp_path)
    with pytest.raises(UserError, match=r"gaussians.ply not found.*real-object sets have none"):
        volume.main([str(ckpt), "--data", str(root), "--split", "train", "--assets", "3"])
