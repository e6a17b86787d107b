"""``python -m physgm.bench material-probe`` on a tiny data set whose two materials look nothing alike."""

from __future__ import annotations

from pathlib import Path

import pytest

from physgm.bench import material_probe
from physgm.data.format import load_asset
from physgm.data.synth import SynthConfig, asset_id, generate


@pytest.fixture(scope="module")
def two_materials(tmp_path_factory) -> Path:
    """Glass (faint, translucent) and stone (opaque, grey) at 32 px: 2 test assets of each, the rest train."""
    root = tmp_path_factory.mktemp("probe") / "data"
    cfg = SynthConfig(
        count=16, seed=0, resolution=32, gaussians=300, video_fraction=0.0, materials=["glass", "stone"]
    )
    summary = generate(cfg, root, workers=1, progress=False)
    assert summary["done"] == 16, summary["failures"]
    by_material: dict[str, list[str]] = {}
    for i in range(16):
        by_material.setdefault(load_asset(root / asset_id(i)).physical.material, []).append(asset_id(i))
    assert sorted(by_material) == ["glass", "stone"] and min(map(len, by_material.values())) >= 4, by_material
    test = [ids[0] for ids in by_material.values()] + [ids[1] for ids in by_material.values()]
    train = [i for ids in by_material.values() for i in ids if i not in test]
    (root / "splits" / "train.txt").write_text("\n".join(train) + "\n")
    (root / "splits" / "test.txt").write_text("\n".join(test) + "\n")
    return root


def test_probe_separates_materials_that_look_different(two_materials):
    # A step budget, not a wall-clock one: on a loaded machine 8 s were too few steps to separate them.
    report = material_probe.main(
        ["--data", str(two_materials), "--steps", "600", "--seconds", "600", "--batch", "16"]
    )
    assert report["steps"] == 600
    assert report["test_assets"] == 4 and report["resolution"] == [32, 32]
    assert report["majority_class_accuracy"] == 0.5
    assert report["test_accuracy_4_views"] == 1.0, report
    assert report["test_accuracy_1_view"] >= 0.75, report
    assert report["train_accuracy_4_views"] >= 0.9, report  # 8 training assets, two easy classes


def test_probe_tests_on_another_folder(two_materials, tmp_path):
    """--test-data takes the test split from a second folder (a larger set tested on a smaller one's)."""
    other = tmp_path / "other"
    (other / "splits").mkdir(parents=True)
    test_ids = (two_materials / "splits" / "test.txt").read_text().split()[:2]
    for asset in test_ids:
        (other / asset).symlink_to(two_materials / asset)
    (other / "splits" / "test.txt").write_text("\n".join(test_ids) + "\n")
    report = material_probe.main(
        ["--data", str(two_materials), "--test-data", str(other), "--seconds", "2", "--batch", "8"]
    )
    assert report["test_data"] == str(other) and report["test_assets"] == 2, report
    assert report["data"] == str(two_materials), report


def test_probe_refuses_an_empty_split(two_materials, tmp_path):
    (two_materials / "splits" / "test.txt").rename(tmp_path / "test.txt")
    try:
        (two_materials / "splits" / "test.txt").write_text("# nothing here\n")
        with pytest.raises(ValueError, match="lists no assets"):
            material_probe.main(["--data", str(two_materials), "--seconds", "1"])
    finally:
        (tmp_path / "test.txt").replace(two_materials / "splits" / "test.txt")
