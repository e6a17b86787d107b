"""The pipeline's pieces against references: framing, placement, floor, physics rules, checkpoints."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.model_configs import small_config

ROOT = Path(__file__).resolve().parents[2]


def test_training_fill_matches_the_synthetic_renders(tiny_dataset):
    """The photo framing constant is the median fill of the canonical view in synthetic assets."""
    from PIL import Image

    from physgm.pipeline.prepared_input import TRAINING_FILL

    fills = []
    for asset in sorted(p for p in tiny_dataset.iterdir() if (p / "rgba").is_dir()):
        alpha = np.asarray(Image.open(asset / "rgba" / "000.png").convert("RGBA"))[..., 3] > 127
        ys, xs = np.nonzero(alpha)
        if len(ys):  # a thin plate seen edge-on at 32 px can vanish
            fills.append(max(np.ptp(ys) + 1, np.ptp(xs) + 1) / alpha.shape[1])
    assert len(fills) >= 8
    assert abs(float(np.median(fills)) - TRAINING_FILL) < 0.1


def test_photo_input_uses_the_canonical_camera(examples):
    from physgm.cameras import orbit_cameras
    from physgm.data.format import CAMERA_RADIUS, FOV_DEG
    from physgm.pipeline.prepared_input import TRAINING_FILL, prepare_input

    inp = prepare_input(examples / "metal_can.png", 64)
    ref = orbit_cameras([0.0], [0.0], CAMERA_RADIUS, FOV_DEG, 64, 64)
    torch.testing.assert_close(inp.c2w, ref.c2w)
    torch.testing.assert_close(inp.Ks, ref.Ks)
    assert inp.images.shape == (1, 3, 64, 64) and inp.masks.shape == (1, 1, 64, 64)
    ys, xs = np.nonzero(inp.masks[0, 0].numpy() > 0.5)
    side = max(np.ptp(ys) + 1, np.ptp(xs) + 1)
    assert side == pytest.approx(TRAINING_FILL * 64, abs=2)  # framed like the training renders
    assert (ys.min() + ys.max()) / 2 == pytest.approx(31.5, abs=1.5) and (
        xs.min() + xs.max()
    ) / 2 == pytest.approx(31.5, abs=1.5)
    # white background like the training inputs: the photo's RGBA over white, so only the render's
    # faint haze (alpha < 0.1 here) tints the ring outside the framed object's square
    frame = torch.ones(64, 64, dtype=torch.bool)
    frame[3:-3, 3:-3] = False
    assert float(inp.images[0][:, inp.masks[0, 0] == 0].min()) > 0.99
    assert float(inp.masks[0, 0][frame].max()) < 0.1 and float(inp.images[0][:, frame].median()) > 0.99


def _object_box(images: torch.Tensor) -> torch.Tensor:  # [V, 3, S, S] on white -> [V, 4] in [0, 1]
    boxes = []
    for m in images.min(dim=1).values < 0.9:
        ys, xs = torch.nonzero(m, as_tuple=True)
        boxes.append(torch.stack([ys.min(), ys.max() + 1, xs.min(), xs.max() + 1]).float() / m.shape[-1])
    return torch.stack(boxes)


def _detail(images: torch.Tensor) -> float:  # [V, 3, 224, 224]: what a 64 px copy cannot hold
    import torch.nn.functional as F

    small = F.interpolate(images, size=(64, 64), mode="bilinear", antialias=True)
    return float((images - F.interpolate(small, size=(224, 224), mode="bilinear")).abs().mean())


@pytest.mark.parametrize("name", ["basketball.png", "plasticine_views"])
def test_classifier_views_have_the_input_framing_at_224_px(examples, name):
    import torch.nn.functional as F

    from physgm.pipeline.prepared_input import prepare_input

    inp = prepare_input(examples / name, 64)
    v = inp.images.shape[0]
    assert inp.classifier_images.shape == (v, 3, 224, 224)
    # the same crop, to a pixel of the 64 px input
    assert float((_object_box(inp.classifier_images) - _object_box(inp.images)).abs().max()) < 1.5 / 64
    # with detail the input lost (measured 1.7-1.8x that of the input brought to 224 px)
    upsampled = F.interpolate(inp.images, size=(224, 224), mode="bilinear")
    assert _detail(inp.classifier_images) > 1.4 * _detail(upsampled)


@pytest.mark.parametrize(("az", "el", "margin"), [(0.0, 0.0, 1.15), (35.0, 20.0, 1.0), (-120.0, -10.0, 1.5)])
def test_framing_camera_fits_the_box(az, el, margin):
    from physgm.pipeline.staging import framing_camera

    lo, hi = np.array([-0.1, -0.05, 0.0]), np.array([0.1, 0.05, 0.4])
    cam = framing_camera(lo, hi, az, el, 34.0, 64, 48, margin)
    corners = torch.tensor(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    vm = cam.viewmats[0].double()
    pc = corners @ vm[:3, :3].T + vm[:3, 3]
    assert bool((pc[:, 2] > 0).all())
    K = cam.Ks[0].double()
    u = (K[0, 0] * pc[:, 0] / pc[:, 2]).abs() / (cam.width / 2)
    v = (K[1, 1] * pc[:, 1] / pc[:, 2]).abs() / (cam.height / 2)
    # The tightest corner sits exactly on the 1 / margin frame, none outside it.
    assert float(torch.maximum(u, v).max()) == pytest.approx(1.0 / margin, abs=1e-5)
    centre = cam.c2w[0, :3, 3].double().numpy() - (lo + hi) / 2
    ref = np.array(
        [
            math.cos(math.radians(el)) * math.cos(math.radians(az)),
            math.cos(math.radians(el)) * math.sin(math.radians(az)),
            math.sin(math.radians(el)),
        ]
    )
    np.testing.assert_allclose(centre / np.linalg.norm(centre), ref, atol=1e-5)


def test_the_clip_region_grows_to_hold_a_body_that_left_the_planned_one():
    """The output camera's region: unchanged while a run stays inside the planned region, grown to
    the middle 98 % of the particles of a body that leaves it, and not pulled out by 1 % of strays."""
    from physgm.pipeline.staging import clip_region

    rng = np.random.default_rng(0)
    lo, hi = np.array([-0.2, -0.2, 0.0]), np.array([0.2, 0.2, 0.6])
    body = rng.uniform(-0.05, 0.05, (1000, 3)) + np.array([0.0, 0.0, 0.1])  # [P, 3] m, a 10 cm cube
    inside = np.stack([body + np.array([0.0, 0.0, 0.02 * t]) for t in range(10)])  # rises 18 cm
    same_lo, same_hi = clip_region(lo, hi, [inside])
    assert np.array_equal(same_lo, lo) and np.array_equal(same_hi, hi)
    # Rolls 1 m along +x: the region reaches the body's last frame, at most its whole extent.
    rolled = np.stack([body + np.array([0.1 * t, 0.0, 0.0]) for t in range(11)])
    grown_lo, grown_hi = clip_region(lo, hi, [inside, rolled])
    assert np.array_equal(grown_lo, lo)
    assert 1.0 + 0.04 < grown_hi[0] <= 1.0 + 0.05
    assert np.array_equal(grown_hi[1:], hi[1:])
    # 1 % of the particles splashed 5 m away leave it as it was.
    splashed = np.repeat(body[None], 5, axis=0)
    splashed[:, :10, 0] += np.linspace(0.0, 5.0, 5)[:, None]
    assert np.array_equal(clip_region(lo, hi, [splashed])[1], hi)
    with pytest.raises(ValueError, match="share"):
        clip_region(lo, hi, [inside], share=0.0)


def test_box_in_view_tells_a_box_the_frame_holds():
    from physgm.pipeline.staging import box_in_view, framing_camera

    lo, hi = np.array([-0.1, -0.1, 0.0]), np.array([0.1, 0.1, 0.3])
    cam = framing_camera(lo, hi, 0.0, 10.0, 34.0, 64, 64, 1.15)  # on +x, looking back at the box
    assert box_in_view(cam, lo, hi)
    assert box_in_view(cam, lo, hi + np.array([0.0, 0.01, 0.0]))  # inside the 15 % margin
    assert not box_in_view(cam, lo, hi + np.array([0.0, 0.2, 0.0]))  # out across the view
    eye = cam.c2w[0, :3, 3].double().numpy()
    assert not box_in_view(cam, lo, np.maximum(hi, eye + 0.1))  # reaches behind the camera


def test_place_object_scales_centres_and_ignores_strays():
    from physgm.gaussians import Gaussians
    from physgm.pipeline.staging import place_object

    gen = torch.Generator().manual_seed(0)
    n = 2000
    means = torch.rand(n, 3, generator=gen) * torch.tensor([1.0, 0.5, 0.25]) + torch.tensor([3.0, 1.0, -2.0])
    means[0] = torch.tensor([50.0, 50.0, 50.0])  # one stray Gaussian far away
    g = Gaussians(
        means,
        torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        torch.full((n, 3), 0.01),
        torch.ones(n),
        torch.rand(n, 3, generator=gen),
    )
    p = place_object(g, 0.2, 0.0, 0.05)
    body = p.gaussians.means[1:]
    assert float((body.amax(0) - body.amin(0)).max()) == pytest.approx(0.2, rel=0.01)
    assert float(body[:, 2].min()) == pytest.approx(0.0, abs=2e-3)
    np.testing.assert_allclose(((body.amax(0) + body.amin(0)) / 2)[:2].numpy(), [0, 0], atol=2e-3)
    assert float(p.gaussians.scales[0, 0]) == pytest.approx(0.01 * p.scale)
    # object_to_world maps the input frame to the world.
    h = (
        torch.cat([g.means.double(), torch.ones(n, 1, dtype=torch.float64)], 1)
        @ torch.from_numpy(p.object_to_world).T
    )
    torch.testing.assert_close(h[:, :3].float(), p.gaussians.means, atol=1e-5, rtol=1e-5)


def test_floor_image_matches_the_ray_plane_intersection():
    from physgm.cameras import orbit_cameras
    from physgm.pipeline.staging import floor_image

    cam_h, res, tile = 0.3, 64, 0.05
    cam = orbit_cameras([0.0], [0.0], 1.0, 40.0, res, res, target=(0.0, 0.0, cam_h))
    bg = np.array([1.0, 1.0, 1.0])
    img = floor_image(cam, 0.0, tile, bg, supersample=1)
    assert np.all(img[: res // 2] == 1.0)  # above the horizon: background only
    f, c = float(cam.Ks[0, 0, 0]), res / 2
    for row in (40, 50, 63):
        for col in (10, 32, 60):
            # Camera at (1, 0, h) looking along -x: image right is world +y, image down is world -z.
            ray = np.array([-1.0, (col + 0.5 - c) / f, -(row + 0.5 - c) / f])
            t = cam_h / -ray[2]
            hit = np.array([1.0, 0.0, cam_h]) + t * ray
            shade = 0.78 if (math.floor(hit[0] / tile) + math.floor(hit[1] / tile)) % 2 else 0.86
            fade = math.exp(-math.hypot(hit[0] - 1.0, hit[1]) / (40 * tile))
            assert img[row, col, 0] == pytest.approx(fade * shade + (1 - fade), abs=1e-4)


def _posterior(material: str, log10_E: float, nu: float):
    from physgm.model.posterior import PhysicsPosterior, normalise_log10_E, normalise_nu
    from physgm.physics.materials import MATERIAL_NAMES

    logits = torch.zeros(1, len(MATERIAL_NAMES))
    logits[0, MATERIAL_NAMES.index(material)] = 3.0
    return PhysicsPosterior(
        logits,
        normalise_log10_E(torch.tensor([log10_E])),
        torch.tensor([-4.0]),
        normalise_nu(torch.tensor([nu])),
        torch.tensor([-6.0]),
    )


def test_physics_choice_rules():
    from physgm.model.posterior import NU_MAX
    from physgm.physics.materials import get_material
    from physgm.pipeline import UserError
    from physgm.pipeline.config import PhysicsOverrides
    from physgm.pipeline.physics_choice import NU_MAX as PIPELINE_NU_MAX
    from physgm.pipeline.physics_choice import choose_physics

    assert PIPELINE_NU_MAX == NU_MAX
    post = _posterior("rubber", 6.0, 0.45)
    (mean,) = choose_physics(post, PhysicsOverrides(), seed=0)
    assert (mean.material, mean.E, mean.nu) == (
        "rubber",
        pytest.approx(1e6, rel=1e-4),
        pytest.approx(0.45, abs=1e-5),
    )
    assert mean.why["material"] == "posterior mean" and mean.density is None
    # A material override keeps a predicted E inside its range, projects one outside it.
    metal = get_material("metal")
    (m,) = choose_physics(post, PhysicsOverrides(material="metal"), seed=0)
    assert m.material == "metal" and m.E == pytest.approx(metal.E_range[0]) and "projected" in m.why["E"]
    # So does a predicted material: a "plastic" predicted with a rubber's E runs at plastic's lowest E.
    plastic = get_material("plastic")
    (p,) = choose_physics(_posterior("plastic", 6.9, 0.35), PhysicsOverrides(), seed=0)
    assert p.E == pytest.approx(plastic.E_range[0]) and "projected onto the plastic range" in p.why["E"]
    assert p.why["material"] == "posterior mean" and plastic.nu_range[0] <= p.nu <= plastic.nu_range[1]
    (e,) = choose_physics(post, PhysicsOverrides(E=3e4, nu=0.2, density=900.0), seed=0)
    assert (e.material, e.E, e.nu, e.density) == ("rubber", 3e4, 0.2, 900.0)
    # A .ply input: the material is required, E and nu come from the table.
    with pytest.raises(UserError, match="physics.material"):
        choose_physics(None, PhysicsOverrides(), seed=0)
    with pytest.raises(UserError, match="samples"):
        choose_physics(None, PhysicsOverrides(material="wood", samples=2), seed=0)
    (w,) = choose_physics(None, PhysicsOverrides(material="wood"), seed=0)
    wood = get_material("wood")
    assert (w.E, w.nu) == (wood.E, wood.nu)
    # Samples: K draws, reproducible with the seed, spread like the posterior (std 10^... here small).
    a = choose_physics(post, PhysicsOverrides(samples=4), seed=3)
    b = choose_physics(post, PhysicsOverrides(samples=4), seed=3)
    assert [r.name for r in a] == ["mean", "sample0", "sample1", "sample2", "sample3"]
    assert [r.E for r in a] == [r.E for r in b]
    std = float(post.log10_E_std[0])
    # A draw of the posterior's material keeps its E; a draw of another material is projected onto its range.
    for r in a[1:]:
        lo, hi = get_material(r.material).E_range
        assert abs(math.log10(r.E) - 6.0) < 5 * std if r.material == "rubber" else lo <= r.E <= hi


def test_checkpoint_layout_is_lightnings(tmp_path):
    """save_checkpoint writes what LitPretrain.load_from_checkpoint and load_model read, the same net."""
    from physgm.model import PhysGM
    from physgm.model.checkpoint import input_size, load_model, save_checkpoint
    from physgm.train.pretrain import LitPretrain

    torch.manual_seed(1)
    model = PhysGM(small_config(), load_pretrained=False).eval()
    path = tmp_path / "m.ckpt"
    save_checkpoint(model, path)
    lit = LitPretrain.load_from_checkpoint(path, map_location="cpu")
    loaded, ckpt = load_model(path)
    for net in (lit.model, loaded):
        for (k, a), (_, b) in zip(model.state_dict().items(), net.state_dict().items(), strict=True):
            torch.testing.assert_close(a, b, msg=k)
    assert input_size(loaded, ckpt.hparams) == 32 and ckpt.summary()["format_version"] == 1


def test_run_folder_commit(tmp_path):
    from physgm.pipeline import UserError
    from physgm.pipeline.outputs import RunFolder

    target = tmp_path / "a" / "run"
    folder = RunFolder(target)
    with folder as tmp:
        (tmp / "x.txt").write_text("1")
        assert not target.exists()
        folder.commit()
    assert (target / "x.txt").read_text() == "1"
    with pytest.raises(UserError, match="not empty"):
        RunFolder(target)
    empty = tmp_path / "hydra_made"
    empty.mkdir()
    folder = RunFolder(empty)
    with folder as tmp:
        (tmp / "y.txt").write_text("2")
        folder.commit()
    assert (empty / "y.txt").read_text() == "2"


def test_keyframes_and_ply_up_axis():
    from physgm.gaussians import Gaussians
    from physgm.pipeline.outputs import keyframe_indices
    from physgm.pipeline.prepared_input import UP_ROTATIONS, rotate_gaussians

    assert keyframe_indices(50, 5) == [0, 12, 24, 37, 49]
    assert keyframe_indices(3, 5) == [0, 1, 2]
    gen = torch.Generator().manual_seed(0)
    q = torch.nn.functional.normalize(torch.randn(5, 4, generator=gen), dim=-1)
    g = Gaussians(
        torch.eye(3).repeat(2, 1)[:5],
        q,
        torch.rand(5, 3, generator=gen) + 0.1,
        torch.ones(5),
        torch.rand(5, 3, generator=gen),
    )
    for up, axis in (("y", [0.0, 1.0, 0.0]), ("-y", [0.0, -1.0, 0.0])):
        rot = UP_ROTATIONS[up]
        np.testing.assert_allclose(rot @ np.array(axis), [0, 0, 1], atol=1e-12)
        r = rotate_gaussians(g, rot)
        R = torch.from_numpy(rot).float()
        torch.testing.assert_close(r.covariances(), R @ g.covariances() @ R.T, atol=1e-5, rtol=1e-5)


def test_default_config():
    from hydra import compose, initialize_config_dir

    from physgm.pipeline import from_hydra

    overrides = ["input=x.png", "paths.output_dir=/tmp/x"]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        hydra_cfg = compose("simulate", overrides=overrides, return_hydra_config=True).hydra
        cfg = compose("simulate", overrides=overrides)
    # Hydra's run folder is the pipeline's output folder, and Hydra writes nothing into it.
    assert hydra_cfg.run.dir == "/tmp/x" and hydra_cfg.output_subdir is None
    assert hydra_cfg.job_logging.handlers.keys() == {"console"}
    run = from_hydra(cfg)
    assert (run.output.resolution, run.output.frames, run.output.fps, run.scene) == (256, 50, 25.0, "drop")
    assert str(run.ckpt) == "checkpoints/physgm_tiny.ckpt" and run.renderer["backend"] == "warp"
    assert run.planner["bound_px"] > 0 and run.solver["cfl"] > 0


@pytest.mark.parametrize(
    "setting", ["output.gif", "output.frame_plys", "output.floor", "output.progress", "object.stand"]
)
def test_a_true_false_setting_given_anything_else_is_an_error(setting):
    # Before, Python's truth took "maybe" (or "no") as true, and the run went on doing the opposite.
    from hydra import compose, initialize_config_dir

    from physgm.errors import UserError
    from physgm.pipeline import from_hydra

    overrides = ["input=x.png", "paths.output_dir=/tmp/x"]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        ok = from_hydra(compose("simulate", overrides=[*overrides, f"{setting}=false"]))
        bad = compose("simulate", overrides=[*overrides, f"{setting}=maybe"])
    section, name = setting.split(".")
    assert getattr(ok if section == "object" else ok.output, name) is False
    with pytest.raises(UserError, match=rf"{setting}='maybe' must be true or false"):
        from_hydra(bad)


def test_a_run_whose_object_reached_the_region_edge_warns(monkeypatch, capsys, tmp_path):
    """The grid-face walls are a safety net: when they stopped the object, the user is told."""
    from physgm.pipeline import stages

    def future(name: str, faces: int, nu_used: float = 0.45, cells: float = 12.0) -> stages.FutureResult:
        return stages.FutureResult(
            name=name, video=f"{name}.mp4", material="rubber", E=3e7, nu=0.45, mode="mpm",
            integrator="explicit", predicted_error_px=0.0, error_terms={}, px_per_m=500.0,
            E_used=3e7, nu_used=nu_used, particles=100, grid_cells=[8, 8, 8], dx_m=0.01, cells_across=cells,
            substeps=10, rest_frame=None, face_contacts=faces, grid_moves=0, ballistic_frames=1,
            reason="", finite=True, seconds={},
        )  # fmt: skip

    futures = [future("video", 0, nu_used=0.4), future("sample1", 632)]
    cfg = type("C", (), {"scene": "drop", "size_m": 0.2, "planner": {}})()
    sheet = stages._sheet_lines({"posterior": None}, futures, cfg)
    # A capped run says what was simulated, under what was asked for.
    assert sheet.count("    run as E=3e+07 nu=0.40") == 1
    assert sheet.index("    run as E=3e+07 nu=0.40") == sheet.index("  video: rubber E=3e+07 nu=0.45") + 1
    assert sheet.count("    held by the region's edge (see the warning)") == 1
    assert sheet.index("    held by the region's edge (see the warning)") == len(sheet) - 1  # under sample1
    result = stages.RunResult({"seconds": {"total": 1.0}, "object": {"base": None}}, futures)
    monkeypatch.setattr(
        stages, "from_hydra", lambda cfg: type("C", (), {"output_dir": tmp_path, "planner": {}})()
    )
    monkeypatch.setattr(stages, "run_pipeline", lambda cfg: result)
    stages.run(None)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: sample1.mp4: the object reached the edge")
    assert "632 grid-node updates" in err[0] and "planner.spread_factor=2" in err[0]
    # A grid under half the planner's cells across the object is reported too; 9.4 cells is not.
    futures[0] = future("video", 0, cells=2.1)
    futures.append(future("sample2", 0, cells=9.4))
    stages.run(None)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and err[0].startswith(
        "warning: video.mp4: the object was simulated with 2.1 grid cells"
    )
    assert "planner.cells_across=12" in err[0] and "raise planner.max_cells" in err[0]
    sheet = stages._sheet_lines({"posterior": None}, futures, cfg)
    assert sheet.count("    on a coarse grid, 2.1 cells across (see the warning)") == 1
    assert not any("coarse" in line for line in sheet[sheet.index("  sample2: rubber E=3e+07 nu=0.45") :])


def test_a_scene_axis_faces_the_camera_and_a_stretch_pulls_a_tall_body_along_its_height():
    """Without an axis from the user, a push or stretch runs along the horizontal axis most across
    the view; a stretch pulls a taller body vertically unless the camera looks down on it."""
    from physgm.pipeline.config import SceneSettings
    from physgm.pipeline.staging import direction
    from physgm.sim.scenes import load_scene_config

    stretch, push = (SceneSettings(load_scene_config(n), {}) for n in ("stretch", "push"))
    side = direction(0.0, 15.0)  # camera on +x: y is across the view
    wide, tall = [0.2, 0.2, 0.1], [0.1, 0.1, 0.3]
    assert stretch.facing(side, wide).settings["axis"] == 1
    assert stretch.facing(direction(90.0, 15.0), wide).settings["axis"] == 0
    assert stretch.facing(side, tall).settings["axis"] == 2
    assert stretch.facing(side, tall).overrides["axis"] == 2  # handed to the simulator
    assert stretch.facing(direction(0.0, 45.0), tall).settings["axis"] == 1  # looking down on it
    assert push.facing(side, tall).settings["axis"] == 1  # a push stays on the ground
    chosen = SceneSettings({**load_scene_config("stretch"), "axis": 0}, {"axis": 0})
    assert chosen.facing(side, tall) is chosen


def test_the_time_guard_sums_the_futures_and_applies_on_the_cpu_only(make_cfg, blob_ply):
    """Two samples under the limit each but over it together stop the run, naming the slower;
    on CUDA (no throughput known) or with no limit, nothing stops."""
    from types import SimpleNamespace

    from physgm.errors import UserError
    from physgm.pipeline.stages import GUARD_THROUGHPUT, check_time

    def future(name: str, seconds: float):
        plan = SimpleNamespace(mode="mpm", E_used=2e11, substeps_per_frame=40_000)
        prepared = SimpleNamespace(plan=plan, sample=range(1000))
        prepared.predicted_seconds = lambda throughput: seconds * GUARD_THROUGHPUT / throughput
        return SimpleNamespace(label=lambda: f"{name}: metal"), prepared

    futures = [future("mean", 400.0), future("sample0", 500.0)]
    with pytest.raises(UserError, match=r"15 minutes or more, over max_sim_minutes=10 \(sample0: metal: mpm"):
        check_time(futures, make_cfg(blob_ply))
    check_time(futures[:1], make_cfg(blob_ply))  # 6.7 minutes
    check_time(futures, make_cfg(blob_ply, max_sim_minutes=None))
    check_time(futures, make_cfg(blob_ply, max_sim_minutes=20))
    check_time(futures, make_cfg(blob_ply, device="cuda"))
