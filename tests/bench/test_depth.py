"""The one-view depth benchmark: side over front silhouette, the model's against the object's."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from physgm.bench import depth
from physgm.bench.e2e import random_checkpoint
from physgm.data.format import CAMERA_RADIUS
from physgm.errors import UserError
from physgm.gaussians import Gaussians


def _box(width: float, deep: float, n: int = 24) -> Gaussians:
    """Small opaque Gaussians filling a box ``deep`` along x (the canonical camera's axis) and
    ``width`` along y and z."""
    x, y, z = torch.meshgrid(
        *(torch.linspace(-extent / 2, extent / 2, n) for extent in (deep, width, width)), indexing="ij"
    )
    means = torch.stack([x, y, z], -1).reshape(-1, 3)
    step = width / (n - 1)
    return Gaussians(
        means=means,
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(len(means), 1),
        scales=torch.full((len(means), 3), 0.15 * step),
        opacities=torch.full((len(means),), 0.9),
        colors=torch.full((len(means), 3), 0.5),
    )


def test_silhouette_width_counts_the_columns_from_the_first_to_the_last_opaque_one():
    alpha = np.zeros((8, 10))
    alpha[3, 2] = 0.6
    alpha[5, 7] = 0.5
    alpha[4, 9] = 0.49  # under the threshold
    assert depth.silhouette_width(alpha) == 6
    assert depth.silhouette_width(np.zeros((4, 4))) == 0


@pytest.mark.parametrize("deep", [0.2, 0.4, 0.8])
def test_a_box_reads_its_depth_over_its_width(deep):
    # From azimuth 0 the box shows its 0.4 m width, from azimuth 90 its depth, each at the distance of
    # its nearest face (perspective): d / (R - w / 2) over w / (R - d / 2), R the camera's distance.
    w, r = 0.4, CAMERA_RADIUS
    ratio = depth.gaussians_ratio(_box(w, deep), 256)
    assert ratio == pytest.approx((deep / (r - w / 2)) / (w / (r - deep / 2)), rel=0.02)
    box = _box(w, deep)
    assert depth.gaussians_ratio(box[torch.zeros(len(box.means), dtype=torch.bool)], 64) == 0.0


def _rectangles(view_file, width_px: int) -> None:
    size = Image.open(view_file).size[0]
    rgba = np.zeros((size, size, 4), np.uint8)
    left = (size - width_px) // 2
    rgba[size // 4 : 3 * size // 4, left : left + width_px] = 255
    Image.fromarray(rgba, "RGBA").save(view_file)


def test_the_truth_is_read_from_the_views_at_azimuth_0_and_90(tiny_dataset, tmp_path):
    root = tmp_path / "copy"
    shutil.copytree(tiny_dataset, root)
    from physgm.data.format import load_asset, read_split

    asset = load_asset(root / read_split(root, "train")[0])
    front, side = depth._view(asset, 0.0), depth._view(asset, 90.0)
    assert (asset.azimuth_deg[front], asset.elevation_deg[front]) == (0.0, 0.0)
    assert (asset.azimuth_deg[side], asset.elevation_deg[side]) == (90.0, 0.0)
    _rectangles(asset.view_files[front], 20)
    _rectangles(asset.view_files[side], 10)
    assert depth.true_ratio(load_asset(asset.path)) == 0.5  # any other pair of views would not give it


def test_report_scores_each_asset_as_predicted_over_true(tiny_dataset, tmp_path, capsys):
    ckpt = random_checkpoint(tmp_path)
    report = depth.main([str(ckpt), "--data", str(tiny_dataset), "--split", "train", "--assets", "3"])
    assert json.loads(capsys.readouterr().out) == report
    assert report["assets"] == 3 and len(report["per_asset"]) == 3
    for row in report["per_asset"]:
        assert row["true"] > 0 and math.isfinite(row["predicted"])
        assert row["score"] == pytest.approx(row["predicted"] / row["true"])
    scores = sorted(r["score"] for r in report["per_asset"])
    assert report["score"]["median"] == pytest.approx(scores[1])
    assert report["skipped"] == {}


def test_an_asset_whose_view_shows_nothing_is_skipped_with_the_reason(tiny_dataset, tmp_path):
    root = tmp_path / "copy"
    shutil.copytree(tiny_dataset, root)
    from physgm.data.format import load_asset, read_split

    ids = read_split(root, "train")[:3]
    asset = load_asset(root / ids[1])
    faint = np.asarray(Image.open(asset.view_files[depth._view(asset, 90.0)])).copy()
    faint[..., 3] = np.minimum(faint[..., 3], 100)  # alpha under 0.5 everywhere: glass seen faintly
    Image.fromarray(faint, "RGBA").save(asset.view_files[depth._view(asset, 90.0)])
    report = depth.main(
        [str(random_checkpoint(tmp_path)), "--data", str(root), "--split", "train", "--assets", "3"]
    )
    assert [r["asset"] for r in report["per_asset"]] == [ids[0], ids[2]]
    assert list(report["skipped"]) == [ids[1]] and "translucent" in report["skipped"][ids[1]]


def test_bad_input_is_a_clear_error(tiny_dataset, tmp_path):
    with pytest.raises(UserError, match="not found"):
        depth.main([str(tmp_path / "none.ckpt"), "--data", str(tmp_path)])
    ckpt = tmp_path / "x.ckpt"
    ckpt.write_bytes(b"")
    with pytest.raises(UserError, match="physgm.data.real_objects"):
        depth.main([str(ckpt), "--data", str(tmp_path)])
    # A folder of posed views without azimuths (a nerfstudio scene, say) cannot say which view is the side.
    root = tmp_path / "copy"
    shutil.copytree(tiny_dataset, root)
    from physgm.data.format import load_asset, read_split

    asset = load_asset(root / read_split(root, "train")[0])
    cameras = json.loads((asset.path / "cameras.json").read_text())
    for frame in cameras["frames"]:
        frame.pop("azimuth_deg", None)
    (asset.path / "cameras.json").write_text(json.dumps(cameras))
    with pytest.raises(UserError, match="no views at elevation 0 and azimuth 0 and 90"):
        depth.true_ratio(load_asset(asset.path))
