"""Readers: folders written in other tools' layouts load as the project's cameras and labels.

Each test writes a small folder the way that tool writes it and checks the cameras (or labels)
against values worked out by hand in the comments.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image

from physgm.data.check import check_asset
from physgm.data.format import AssetError, load_asset
from physgm.data.readers.physgm_release import RELEASE_MATERIALS, canonical_material
from physgm.errors import UserError
from physgm.physics.materials import MATERIAL_NAMES, get_material
from physgm.pipeline.prepared_input import _read_cameras


def _png(path, w, h) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    rgba = np.zeros((h, w, 4), np.uint8)
    rgba[h // 4 : 3 * h // 4, w // 4 : 3 * w // 4] = (200, 100, 50, 255)  # an opaque square in the middle
    Image.fromarray(rgba).save(path)


def _physical(folder, material="wood", E=1e10, nu=0.35) -> None:
    (folder / "physical.json").write_text(json.dumps({"material": material, "E": E, "nu": nu}))


def _project(asset, i, point) -> np.ndarray:
    """Pixel (u, v) of a world point in view i (OpenCV pinhole)."""
    c2w, K = asset.cameras.c2w[i].double().numpy(), asset.cameras.Ks[i].double().numpy()
    cam = np.linalg.inv(c2w) @ np.append(point, 1.0)
    uvw = K @ cam[:3]
    return uvw[:2] / uvw[2]


# A camera 2 m out on +x, level, looking at the origin, world +z up. In OpenGL axes its
# camera-to-world columns are right (0, 1, 0), up (0, 0, 1), back (1, 0, 0); in OpenCV axes right
# (0, 1, 0), down (0, 0, -1), forward (-1, 0, 0).
GL_C2W = [[0, 0, 1, 2], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]
CV_C2W = [[0, 0, -1, 2], [1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]]


def _cameras_json(folder, convention, c2w) -> None:
    _png(folder / "rgba" / "000.png", 32, 32)
    frame = {"file": "rgba/000.png", "c2w": c2w, "fx": 40.0, "fy": 40.0, "cx": 16.0, "cy": 16.0,
             "width": 32, "height": 32}  # fmt: skip
    d = {"frames": [frame]} if convention is None else {"convention": convention, "frames": [frame]}
    (folder / "cameras.json").write_text(json.dumps(d))
    _physical(folder)


@pytest.mark.parametrize(
    "convention, c2w", [("opengl", GL_C2W), ("OpenGL", GL_C2W), ("opencv", CV_C2W), (None, CV_C2W)]
)
def test_cameras_json_honours_its_convention(tmp_path, convention, c2w):
    _cameras_json(tmp_path, convention, c2w)
    asset = load_asset(tmp_path)
    np.testing.assert_allclose(asset.cameras.c2w[0].numpy(), CV_C2W, atol=1e-7)
    # The origin is straight ahead; a point 0.1 m towards +y (the camera's right) lands
    # f * 0.1 / 2 = 2 px right of the centre, one 0.1 m up (+z) 2 px above it.
    np.testing.assert_allclose(_project(asset, 0, [0, 0, 0]), [16, 16], atol=1e-6)
    np.testing.assert_allclose(_project(asset, 0, [0, 0.1, 0]), [18, 16], atol=1e-6)
    np.testing.assert_allclose(_project(asset, 0, [0, 0, 0.1]), [16, 14], atol=1e-6)


def test_cameras_json_with_an_unknown_convention_is_refused(tmp_path):
    _cameras_json(tmp_path, "directx", GL_C2W)
    with pytest.raises(AssetError, match="unknown convention 'directx'"):
        load_asset(tmp_path)


def test_nerfstudio_transforms_with_shared_and_per_frame_intrinsics(tmp_path):
    _png(tmp_path / "images" / "frame_00001.png", 64, 48)
    _png(tmp_path / "images" / "frame_00002.png", 64, 48)
    transforms = {
        "camera_model": "OPENCV", "fl_x": 100.0, "fl_y": 110.0, "cx": 31.0, "cy": 23.0, "w": 64, "h": 48,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "frames": [
            {"file_path": "images/frame_00001.png", "transform_matrix": GL_C2W},
            # The same camera moved to 3 m, with its own focal length (nerfstudio allows both).
            {"file_path": "images/frame_00002.png", "fl_x": 90.0, "fl_y": 90.0,
             "transform_matrix": [[0, 0, 1, 3], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]},
        ],
    }  # fmt: skip
    (tmp_path / "transforms.json").write_text(json.dumps(transforms))
    _physical(tmp_path, "Rubber", 5e6, 0.48)
    asset = load_asset(tmp_path)
    assert check_asset(tmp_path) == []
    assert [f.name for f in asset.view_files] == ["frame_00001.png", "frame_00002.png"]
    assert (asset.cameras.width, asset.cameras.height) == (64, 48)
    np.testing.assert_allclose(asset.cameras.c2w[0].numpy(), CV_C2W, atol=1e-7)
    np.testing.assert_allclose(asset.cameras.c2w[1, :3, 3].numpy(), [3, 0, 0])
    np.testing.assert_allclose(asset.cameras.Ks[0].numpy(), [[100, 0, 31], [0, 110, 23], [0, 0, 1]])
    np.testing.assert_allclose(asset.cameras.Ks[1].numpy(), [[90, 0, 31], [0, 90, 23], [0, 0, 1]])
    # 0.1 m to the right at 2 m: 100 * 0.1 / 2 = 5 px right of cx; 0.1 m up: 110 * 0.05 = 5.5 px up.
    np.testing.assert_allclose(_project(asset, 0, [0, 0.1, 0]), [36, 23], atol=1e-5)
    np.testing.assert_allclose(_project(asset, 0, [0, 0, 0.1]), [31, 17.5], atol=1e-5)
    # The same folder is a posed-views input of simulate.py.
    files, cams = _read_cameras(tmp_path)
    assert len(files) == 2 and torch.equal(cams.c2w, asset.cameras.c2w)


def test_blender_transforms_with_camera_angle_x_and_extensionless_paths(tmp_path):
    # The NeRF Blender scenes: camera_angle_x in radians, "./train/r_0" meaning r_0.png, no w/h.
    _png(tmp_path / "train" / "r_0.png", 40, 40)
    transforms = {"camera_angle_x": 0.6911112070083618,
                  "frames": [{"file_path": "./train/r_0", "rotation": 0.0126, "transform_matrix": GL_C2W}]}  # fmt: skip  # noqa: E501
    (tmp_path / "transforms.json").write_text(json.dumps(transforms))
    _physical(tmp_path)
    asset = load_asset(tmp_path)
    # f = W / (2 tan(angle / 2)) = 40 / (2 tan(0.34556)) = 55.5556 px (1111.11 px at the scenes' 800 px).
    np.testing.assert_allclose(asset.cameras.Ks[0].numpy(), [[55.55555, 0, 20], [0, 55.55555, 20], [0, 0, 1]],
                               rtol=1e-6)  # fmt: skip
    assert asset.view_files[0] == tmp_path / "train" / "r_0.png"
    np.testing.assert_allclose(asset.cameras.c2w[0].numpy(), CV_C2W, atol=1e-7)


@pytest.mark.parametrize(
    "key, value, message",
    [("k1", -0.05, "lens distortion k1"), ("camera_model", "OPENCV_FISHEYE", "not a pinhole camera")],
)
def test_transforms_with_distortion_is_refused_naming_the_key(tmp_path, key, value, message):
    _png(tmp_path / "a.png", 16, 16)
    transforms = {
        "fl_x": 20.0,
        "w": 16,
        "h": 16,
        key: value,
        "frames": [{"file_path": "a.png", "transform_matrix": GL_C2W}],
    }
    (tmp_path / "transforms.json").write_text(json.dumps(transforms))
    _physical(tmp_path)
    with pytest.raises(AssetError, match=message):
        load_asset(tmp_path)
    with pytest.raises(UserError, match=message):
        _read_cameras(tmp_path)


# Frame 000.png of the authors' example asset (example_data/cake/pose.json in their repository).
CAKE_W2C = [
    [-1.2844618728016414e-07, 1.000000059999987, -1.3535727264606844e-08, 2.201500034538704e-07],
    [0.15517688375667954, 1.3535727264606848e-08, -0.9878867036481709, 1.461266403119547e-08],
    [-0.9878867366481554, -1.2844618728016414e-07, -0.15517688375667954, 1.7067121144449247],
    [0.0, 0.0, 0.0, 1.0],
]


def test_physgm_release_pose_and_capitalised_material(tmp_path):
    _png(tmp_path / "000.png", 64, 64)
    pose = {"scene_name": "0002c6eafa154e8bb08ebafb715a8d46",
            "frames": [{"file_path": "000.png", "w2c": CAKE_W2C, "h": 64, "w": 64, "fx": 64.0, "fy": 64.0,
                        "cx": 32.0, "cy": 32.0}]}  # fmt: skip
    (tmp_path / "pose.json").write_text(json.dumps(pose))
    # Their loader reads E and nu with float(), so strings occur.
    (tmp_path / "physical.json").write_text(json.dumps({"material": "Wood", "E": "1e10", "nu": 0.35}))
    asset = load_asset(tmp_path)
    assert check_asset(tmp_path) == []
    # c2w = inverse(w2c): centre -R^T t = 1.7067 * (0.98789, 0, 0.15518) = (1.68604, 0, 0.26484) m, i.e.
    # 1.7067 m away at elevation asin(0.15518) = 8.93 deg; forward is the third row of w2c,
    # (-0.98789, 0, -0.15518), towards the origin; the camera's down axis (0.15518, 0, -0.98789)
    # points to world -z, so their world is +z up like the project's.
    c2w = asset.cameras.c2w[0].double().numpy()
    np.testing.assert_allclose(c2w[:3, 3], [1.68604, 0.0, 0.26484], atol=1e-5)
    np.testing.assert_allclose(c2w[:3, 2], [-0.98789, 0.0, -0.15518], atol=1e-5)
    np.testing.assert_allclose(c2w[:3, 1], [0.15518, 0.0, -0.98789], atol=1e-5)
    np.testing.assert_allclose(_project(asset, 0, [0, 0, 0]), [32, 32], atol=1e-4)
    phys = asset.physical
    assert phys.material == "wood" and phys.extra["material_as_written"] == "Wood"
    assert phys.E == 1e10 and not phys.true_known and phys.annotation.material == "wood"
    assert phys.annotation.E == 1e10  # quantised to the category grid: 1e10 is a category


def test_every_release_material_name_maps_onto_the_table_in_any_case():
    assert len(RELEASE_MATERIALS) == 14 and "jelly" not in RELEASE_MATERIALS.values()
    for theirs, ours in RELEASE_MATERIALS.items():
        assert ours in MATERIAL_NAMES and get_material(ours).name == ours
        assert (
            canonical_material(theirs)
            == canonical_material(theirs.upper())
            == canonical_material(f" {theirs.lower()} ")
            == ours
        )
    assert canonical_material("Concrete") is None and canonical_material(3) is None


def test_unknown_release_material_names_the_value_and_the_choices(tmp_path):
    _png(tmp_path / "000.png", 64, 64)
    (tmp_path / "pose.json").write_text(json.dumps({"frames": [{"file_path": "000.png", "w2c": CAKE_W2C, "h": 64,  # noqa: E501
                                                               "w": 64, "fx": 64, "fy": 64, "cx": 32, "cy": 32}]}))  # fmt: skip  # noqa: E501
    (tmp_path / "physical.json").write_text(json.dumps({"material": "Concrete", "E": 3e10, "nu": 0.2}))
    with pytest.raises(AssetError, match=r"unknown material 'Concrete' \(known, any case: plastic, wood"):
        load_asset(tmp_path)


def test_shard_samples_store_the_converted_cameras(tmp_path):
    from physgm.data.shards import ShardRecord, asset_to_sample

    _cameras_json(tmp_path, "opengl", GL_C2W)
    (tmp_path / "physical.json").write_text(json.dumps({"material": "Jelly", "E": 1e4, "nu": 0.45}))
    record = ShardRecord({**asset_to_sample(str(tmp_path)), "id": "a"})
    np.testing.assert_allclose(record.c2w[0].numpy(), CV_C2W, atol=1e-7)
    assert record.physical.material == "jelly"
