"""Mesh importer: ray caster against its brute-force twin, analytic silhouettes, colours."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh
from PIL import Image

from physgm.data.appearance import AMBIENT, LIGHT_DIR
from physgm.data.check import check_asset
from physgm.data.format import FOV_DEG, load_asset, read_split
from physgm.data.from_meshes import load_mesh, main
from physgm.data.raycast import cast_rays, cast_rays_brute
from physgm.data.synth import view_cameras


def test_tiled_ray_casting_matches_brute_force():
    mesh = trimesh.creation.torus(0.3, 0.1, major_sections=16, minor_sections=8)
    mesh.apply_transform(trimesh.transformations.random_rotation_matrix(np.random.default_rng(0).random(3)))
    tri = np.asarray(mesh.vertices)[mesh.faces]
    cams, _, _ = view_cameras(24)
    for c in (0, 13, 30):
        c2w, K = cams.c2w[c].double().numpy(), cams.Ks[c].double().numpy()
        fast, slow = cast_rays(tri, c2w, K, 24, 24, tile=8), cast_rays_brute(tri, c2w, K, 24, 24)
        np.testing.assert_array_equal(fast.face, slow.face)
        np.testing.assert_allclose(fast.t, slow.t)
        np.testing.assert_allclose(fast.bary, slow.bary, atol=1e-12)
        assert (fast.face >= 0).sum() > 20


def test_box_import_silhouette_colour_and_format(tmp_path):
    box = trimesh.creation.box(extents=[1.0, 1.0, 1.0])
    box.visual.face_colors = np.tile([200, 60, 30, 255], (12, 1))
    box.export(tmp_path / "crate.ply")
    out = tmp_path / "assets"
    assert (
        main(
            [
                "--meshes",
                str(tmp_path / "crate.ply"),
                "--material",
                "wood",
                "--out",
                str(out),
                "--resolution",
                "64",
                "--split",
                "val",
            ]
        )
        == 0
    )
    asset = load_asset(out / "crate")
    assert check_asset(out / "crate") == [] and read_split(out, "val") == ["crate"]
    assert asset.physical.material == "wood" and asset.physical.extra["physics_source"] == "material default"
    rgba = asset.load_rgba([0])[0]
    # Normalised: half-diagonal 0.5, so half side h = 0.5 / sqrt(3); the +x face at 1.8 - h m
    # from the azimuth-0 camera spans 2 f h / (1.8 - h) pixels.
    f = 32 / math.tan(math.radians(FOV_DEG / 2))
    h = 0.5 / math.sqrt(3)
    side = 2 * f * h / (1.8 - h)
    assert rgba[..., 3].sum() == pytest.approx(side**2, rel=0.02)
    shade = AMBIENT + (1 - AMBIENT) * LIGHT_DIR[0]  # the face normal is +x
    np.testing.assert_allclose(rgba[32, 32, :3], np.array([200, 60, 30]) / 255 * shade, atol=1.5 / 255)


def test_textured_glb_is_y_up_and_takes_texture_colours(tmp_path):
    # A tall box along +y with a uniform green texture: after the y-up to z-up turn it stands tall.
    box = trimesh.creation.box(extents=[0.4, 1.6, 0.4])
    uv = np.random.default_rng(0).random((len(box.vertices), 2))
    box.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.new("RGB", (8, 8), (20, 180, 40)))
    box.export(tmp_path / "post.glb")
    obj = load_mesh(tmp_path / "post.glb")
    extent = obj.triangles.reshape(-1, 3).max(0) - obj.triangles.reshape(-1, 3).min(0)
    assert extent[2] > 3 * extent[0] and extent[2] > 3 * extent[1]
    colour = obj.sources[0].sample(np.array([0, 5]), np.full((2, 3), 1 / 3))
    factor = obj.sources[0].factor if obj.sources[0].factor is not None else np.ones(3)
    np.testing.assert_allclose(colour, np.tile(np.array([20, 180, 40]) / 255 * factor, (2, 1)), atol=1e-6)


def _import(capsys, *args: str) -> tuple[int, dict]:
    code = main([*args, "--material", "wood", "--resolution", "16", "--supersample", "1"])
    return code, json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def _coloured_box(path, extents, colour) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    box = trimesh.creation.box(extents=extents)
    box.visual.face_colors = np.tile([*colour, 255], (12, 1))
    box.export(path)


def test_same_file_name_in_two_folders_gives_two_assets(tmp_path, capsys):
    # Many mesh collections call every file model.obj: a red cube and a flat green slab.
    meshes, out = tmp_path / "meshes", tmp_path / "assets"
    _coloured_box(meshes / "chair" / "model.obj", [1.0, 1.0, 1.0], [220, 20, 20])
    _coloured_box(meshes / "table" / "model.obj", [1.0, 1.0, 0.2], [20, 220, 20])
    code, report = _import(capsys, "--meshes", str(meshes), "--out", str(out))
    assert code == 0 and report["imported"] == 2 and report["assets_on_disk"] == 2 and report["renamed"] == {}
    assert read_split(out, "train") == ["chair__model", "table__model"]
    chair, table = load_asset(out / "chair__model"), load_asset(out / "table__model")
    assert chair.physical.extra["mesh_file"] == "chair/model.obj"
    assert table.physical.extra["mesh_file"] == "table/model.obj"
    # Two different objects, not one asset written twice: the views differ in colour and area.
    red, green = chair.load_rgba([0])[0], table.load_rgba([0])[0]
    assert red[8, 8, 0] > 0.5 > red[8, 8, 1] and green[8, 8, 1] > 0.5 > green[8, 8, 0]
    assert green[..., 3].sum() < 0.6 * red[..., 3].sum()
    # Importing again is stable: same ids, nothing new, each id once in the split list.
    code, report = _import(capsys, "--meshes", str(meshes), "--out", str(out))
    assert code == 0 and (report["imported"], report["already_present"], report["assets_on_disk"]) == (
        0,
        2,
        2,
    )
    assert read_split(out, "train") == ["chair__model", "table__model"]


def test_colliding_ids_get_hash_suffixes_and_a_clash_on_disk_is_an_error(tmp_path, capsys):
    out = tmp_path / "assets"
    _coloured_box(tmp_path / "a" / "model.obj", [1.0, 1.0, 1.0], [220, 20, 20])
    _coloured_box(tmp_path / "b" / "model.obj", [1.0, 0.3, 1.0], [20, 20, 220])
    code, report = _import(capsys, "--meshes", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out))
    ids = sorted(report["renamed"].values())
    assert code == 0 and report["imported"] == 2 and report["assets_on_disk"] == 2 and len(ids) == 2
    assert all(i.startswith("model-") and len(i) == len("model-") + 8 for i in ids)
    assert sorted(read_split(out, "train")) == ids
    # Same ids on a second run (the suffix hashes the folder name and relative path, not the order).
    code, again = _import(capsys, "--meshes", str(tmp_path / "b"), str(tmp_path / "a"), "--out", str(out))
    assert code == 0 and again["renamed"] == report["renamed"] and again["already_present"] == 2
    # A different object under an id that exists on disk is refused, and the old asset is kept.
    _coloured_box(tmp_path / "c" / "crate.obj", [1.0, 1.0, 1.0], [20, 220, 20])
    code, _ = _import(capsys, "--meshes", str(tmp_path / "c"), "--out", str(out))
    _coloured_box(tmp_path / "d" / "crate.obj", [0.2, 1.0, 1.0], [220, 220, 20])
    before = (out / "crate" / "rgba" / "000.png").read_bytes()
    code, report = _import(capsys, "--meshes", str(tmp_path / "d"), "--out", str(out))
    assert code == 1 and "already exists" in report["failed"][str(tmp_path / "d" / "crate.obj")]
    assert report["imported"] == 0 and report["assets_on_disk"] == 3
    assert (out / "crate" / "rgba" / "000.png").read_bytes() == before
    # An asset joins one split only.
    code, report = _import(capsys, "--meshes", str(tmp_path / "c"), "--out", str(out), "--split", "val")
    assert code == 1 and "another split" in report["failed"]["splits"] and read_split(out, "val") == []
