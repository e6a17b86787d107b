"""Reference-video plumbing: object placement, camera framing, mp4 + json that the checker reads."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from physgm.data.check import check_asset
from physgm.data.format import load_asset
from physgm.data.priors import sample_physics
from physgm.data.procedural import make_object
from physgm.data.video import VideoConfig, place_object, video_camera
from physgm.data.writer import camera_entry, write_json
from physgm.mp4 import read_mp4, write_mp4


def test_object_is_placed_above_ground_and_framed_by_the_paper_camera():
    cfg = VideoConfig()
    phys = sample_physics("rubber", np.random.default_rng(0))
    g = make_object("capsule", phys, 1000, np.random.default_rng(0)).gaussians
    world, T = place_object(g, cfg)
    assert float(world.means[:, 2].min()) == pytest.approx(cfg.drop_height_m, abs=1e-6)
    np.testing.assert_allclose(
        world.means.numpy(), (g.means.double().numpy() @ T[:3, :3].T + T[:3, 3]), atol=1e-6
    )
    for az in cfg.azimuths_deg:
        cam = video_camera(cfg, az, 128)
        centre = cam.c2w[0, :3, 3]
        assert abs(float(centre.norm()) - np.hypot(cfg.radius_m, float(cam.c2w[0, 2, 3]))) < 1e-5
        # Every Gaussian at t = 0 and the ground contact point below the object are in the image.
        pts = torch.cat([world.means, torch.tensor([[0.0, 0.0, 0.0]])])
        cam_pts = pts @ cam.viewmats[0, :3, :3].T + cam.viewmats[0, :3, 3]
        uv = cam_pts[:, :2] / cam_pts[:, 2:] * cam.Ks[0, 0, 0] + cam.Ks[0, :2, 2]
        assert (uv > 0).all() and (uv < 128).all()


def test_mp4_and_metadata_round_trip_and_are_checked(tiny_copy):
    asset_dir = tiny_copy / "syn_000004"
    frames = np.zeros((12, 32, 32, 3), np.uint8)
    frames[:, 8:24, 8:24] = np.linspace(0, 255, 12, dtype=np.uint8)[:, None, None, None]
    (asset_dir / "videos").mkdir()
    write_mp4(asset_dir / "videos" / "drop.mp4", frames, 25.0)
    cam = video_camera(VideoConfig(), -45.0, 32)
    meta = {"scene": "drop", "fps": 25.0, "frames": 12, "camera": camera_entry(cam.c2w[0], cam.Ks[0], 32, 32)}
    write_json(asset_dir / "videos" / "drop.json", meta)
    asset = load_asset(asset_dir)
    assert len(asset.videos) == 1 and asset.videos[0].frames == 12 and asset.videos[0].fps == 25.0
    torch.testing.assert_close(asset.videos[0].cameras.c2w[0], cam.c2w[0])
    assert check_asset(asset_dir) == []
    # Same bytes when written again (bit-exact flags, one encoder thread).
    write_mp4(tiny_copy / "again.mp4", frames, 25.0)
    assert (tiny_copy / "again.mp4").read_bytes() == (asset_dir / "videos" / "drop.mp4").read_bytes()
    meta["frames"] = 50
    (asset_dir / "videos" / "drop.json").write_text(json.dumps(meta))
    assert any("has 12 frames but its json says 50" in p for p in check_asset(asset_dir))
    (asset_dir / "videos" / "drop.json").unlink()
    assert any("no metadata file" in p for p in check_asset(asset_dir))


def test_reference_video_falls_like_free_fall_then_is_checked(tmp_path):
    """A short drop through the real simulator: 5 frames of free fall move the object g t^2 / 2."""
    from physgm.data.video import write_reference_video

    cfg = VideoConfig(n_frames=8)
    phys = sample_physics("jelly", np.random.default_rng(2))
    g = make_object("ellipsoid", phys, 400, np.random.default_rng(2)).gaussians
    info = write_reference_video(tmp_path, g, phys, np.random.default_rng(0), 32, cfg=cfg)
    assert info["mode"] in ("mpm", "rigid")
    frames = read_mp4(tmp_path / "videos" / "drop.mp4").astype(float)
    assert len(frames) == 8
    meta = json.loads((tmp_path / "videos" / "drop.json").read_text())
    assert meta["frames"] == 8 and meta["azimuth_deg"] in (-45.0, 135.0)
    assert meta["height_from"] == "surface"  # what rollouts check before comparing with it

    def centroid_row(img):
        w = (255 - img.mean(-1)).clip(0)  # darkness = object over the white background
        return (w.sum(1) * np.arange(img.shape[0])).sum() / w.sum()

    t = 5 / cfg.fps  # the object is 0.25 m up, so it is still falling freely at 0.2 s
    f = meta["camera"]["fy"]
    expect = f * 0.5 * 9.81 * t**2 / cfg.radius_m
    moved = centroid_row(frames[5]) - centroid_row(frames[0])
    assert 0.75 * expect < moved < 1.25 * expect


def test_a_rubber_reference_video_is_simulated_with_explicit_mpm(tmp_path, monkeypatch):
    """Stage 2 scores explicit rollouts against these videos, so a rubber at nu = 0.49, which the
    default planner would run with the pressure split (were it 12 cells thick: the split's least
    thickness is lowered here), is simulated explicitly here."""
    from physgm.data.priors import TruePhysics
    from physgm.data.video import write_reference_video
    from physgm.sim.planner import choose

    monkeypatch.setattr(choose, "PRESSURE_MIN_CELLS", 0.0)

    phys = TruePhysics("rubber", 5e6, 0.49, 1100.0, 0.6, 0.9)
    g = make_object("ellipsoid", phys, 400, np.random.default_rng(2)).gaussians
    write_reference_video(tmp_path, g, phys, np.random.default_rng(0), 32, cfg=VideoConfig(n_frames=9))
    meta = json.loads((tmp_path / "videos" / "drop.json").read_text())
    assert meta["simulation"]["mode"] == "mpm" and meta["simulation"]["integrator"] == "explicit"
