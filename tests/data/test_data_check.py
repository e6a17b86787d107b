"""The validator finds every planted defect in one pass; load_asset names what is wrong."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from physgm.data.check import check_root, main
from physgm.data.format import AssetError, load_asset


def _edit_json(path: Path, fn) -> None:
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def _set(key, value):
    def fn(d):
        d[key] = value

    return fn


def _nan_camera(d):
    d["frames"][3]["c2w"][0][3] = float("nan")


def _bad_rotation(d):
    d["frames"][1]["c2w"][0][0] = 2.0


def _negative_focal(d):
    d["frames"][2]["fx"] = -10.0


def _annotation_off_grid(d):
    d["annotation"]["E"] = 123.0


# asset index -> (how to damage it, words the report must contain)
DEFECTS = {
    0: (lambda a: (a / "rgba" / "005.png").unlink(), "view image rgba/005.png is missing"),
    1: (
        lambda a: (a / "rgba" / "007.png").write_bytes((a / "rgba" / "007.png").read_bytes()[:40]),
        "007.png is unreadable",
    ),
    2: (lambda a: _edit_json(a / "cameras.json", _nan_camera), "non-finite"),
    3: (lambda a: _edit_json(a / "physical.json", _set("nu", 0.5)), "nu must be in (-1, 0.5)"),
    4: (lambda a: _edit_json(a / "physical.json", _set("E", -3.0)), "E must be positive"),
    5: (
        lambda a: _edit_json(a / "physical.json", _set("material", "unobtainium")),
        "unknown material 'unobtainium'",
    ),
    6: (lambda a: _edit_json(a / "physical.json", _annotation_off_grid), "not one of the categories"),
    7: (
        lambda a: Image.new("RGBA", (16, 16)).save(a / "rgba" / "002.png"),
        "is 16x16 but cameras.json says 32x32",
    ),
    8: (lambda a: Image.new("RGBA", (32, 32)).save(a / "rgba" / "009.png"), "fully transparent"),
    9: (lambda a: (a / "physical.json").unlink(), "missing physical.json"),
    10: (lambda a: (a / "cameras.json").write_text("{not json"), "cameras.json is not valid JSON"),
    11: (lambda a: _edit_json(a / "cameras.json", _bad_rotation), "not orthonormal"),
    12: (lambda a: _edit_json(a / "cameras.json", _negative_focal), "focal lengths must be positive"),
    13: (lambda a: (a / "gaussians.ply").write_bytes(b"ply\nformat nonsense\n"), "gaussians.ply"),
    14: (lambda a: Image.new("RGB", (32, 32), "white").save(a / "rgba" / "004.png"), "no alpha channel"),
}


def test_every_planted_defect_is_reported_in_one_pass(tiny_copy):
    root = tiny_copy
    for i, (damage, _) in DEFECTS.items():
        damage(root / f"syn_{i:06d}")
    with open(root / "splits" / "val.txt", "a") as f:
        f.write("syn_999999\nsyn_000020\n")  # a missing asset, and one already in another split
    report = check_root(root)
    assert report.checked == 24
    assert set(report.assets) == {f"syn_{i:06d}" for i in DEFECTS}  # clean assets are not flagged
    for i, (_, words) in DEFECTS.items():
        problems = report.assets[f"syn_{i:06d}"]
        assert any(words in p for p in problems), (i, problems)
    text = "\n".join(report.dataset)
    assert "syn_999999, which is not an asset folder" in text
    assert "syn_000020 is in both" in text


def test_cli_exit_codes_and_json(tiny_root, tiny_copy, capsys):
    assert main([str(tiny_root)]) == 0
    assert "OK" in capsys.readouterr().out
    _edit_json(tiny_copy / "syn_000001" / "physical.json", _set("nu", 0.7))
    assert main([str(tiny_copy), "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report["bad_assets"] == 1 and "syn_000001" in report["assets"]


def test_load_asset_error_names_asset_and_every_problem(tiny_copy):
    path = tiny_copy / "syn_000002"
    _edit_json(path / "physical.json", _set("E", 0.0))
    (path / "rgba" / "010.png").unlink()
    with pytest.raises(AssetError) as err:
        load_asset(path)
    msg = str(err.value)
    assert "syn_000002" in msg and "E must be positive" in msg and "rgba/010.png is missing" in msg


def test_real_asset_without_annotation_uses_its_labels_as_annotation(tiny_copy):
    path = tiny_copy / "syn_000003"
    # The PhysGM release has material, E and nu only.
    path.joinpath("physical.json").write_text(json.dumps({"material": "rubber", "E": 2.0e6, "nu": 0.47}))
    (path / "gaussians.ply").unlink()
    asset = load_asset(path)
    assert not asset.physical.true_known and asset.gaussians_path is None
    assert asset.physical.annotation.material == "rubber"
    assert asset.physical.annotation.E == 1e6 and asset.physical.annotation.nu == 0.45
    rgba = asset.load_rgba([0])
    assert rgba.dtype == np.float32 and 0 <= rgba.min() and rgba.max() <= 1
