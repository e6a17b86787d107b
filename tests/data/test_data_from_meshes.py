"""Mesh importer: ray caster against its brute-force twin, analytic silhouettes, colours."""

from __future__ import annotations

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
