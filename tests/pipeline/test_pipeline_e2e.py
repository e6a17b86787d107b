"""End to end: each input kind, overrides, posterior samples, scenes, the report and the outputs."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from physgm.pipeline import STAGES, run_pipeline

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def video_frames(path) -> int:
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    count = sum(1 for _ in reader)
    assert tuple(meta["size"]) in {(32, 32), (256, 256)}
    return count


def check_run_folder(run, report, n_videos: int = 1) -> None:
    from physgm.gaussians import read_ply

    cam = report["camera"]  # the planning camera's scale unless a run left its view
    assert cam["px_per_m"] > 0 and (cam["px_per_m"] == cam["px_per_m_planned"]) != cam["reframed"]

    names = {p.name for p in run.iterdir()}
    assert {
        "video.mp4",
        "contact_sheet.png",
        "gaussians.ply",
        "physics.json",
        "report.json",
        "config.json",
    } <= names
    assert sum(n.startswith("video") and n.endswith(".mp4") for n in names) == n_videos
    assert not list(run.parent.glob(f".{run.name}.tmp-*")), "the temporary folder must be gone"
    frames = report["output"]["frames"]
    assert video_frames(run / "video.mp4") == frames
    # Every stage is timed, and the clock adds up.
    secs = report["seconds"]
    assert set(STAGES) | {"total"} == set(secs)
    assert all(math.isfinite(v) and v >= 0 for v in secs.values())
    assert sum(secs[s] for s in STAGES) <= secs["total"] + 1e-2
    assert report["finite"] is True and all(r["finite"] for r in report["runs"])
    assert report["mode"] in {"rigid", "mpm"} and math.isfinite(report["predicted_error_px"])
    assert report["particles"] > 0 and len(report["grid_cells"]) == 3
    # gaussians.ply is the t = 0 state in metres: as large as object.size and on or above the ground,
    # both up to the placement's outlier quantile (a few stray Gaussians do not size the object) and
    # to what following the simulation's particles moves the t = 0 Gaussians from the placed input.
    from physgm.pipeline.staging import OUTLIER_QUANTILE

    g = read_ply(run / "gaussians.ply")
    assert len(g) == report["object"]["gaussians"]
    threshold = report["object"]["mass_opacity"]
    assert 0.005 <= threshold <= 0.05  # sampling.mass_opacity's range
    assert report["object"]["gaussians_with_mass"] == int((g.opacities >= threshold).sum())
    opaque = g.means[g.opacities >= 0.05]
    lo, hi = (opaque.double().quantile(q, dim=0) for q in (OUTLIER_QUANTILE, 1 - OUTLIER_QUANTILE))
    assert float((hi - lo).max()) == pytest.approx(report["object"]["size_m"], rel=0.15)
    assert float(opaque[:, 2].quantile(OUTLIER_QUANTILE)) >= -0.01 * report["object"]["size_m"]
    base = report["object"]["base"]  # null for a .ply or a scene without a ground
    if base is not None:
        from physgm.pipeline.standing import MAX_CUT, TIP_DEG

        assert 0.0 <= base["cut"] <= MAX_CUT and (base["cut"] > 0) == (base["moved"] > 0)
        assert base["cut"] == 0.0 or (base["turn_deg"] > TIP_DEG >= base["turn_after_deg"])
    assert json.loads((run / "report.json").read_text()) == json.loads(json.dumps(report))


def test_photo_with_alpha(make_cfg):
    cfg = make_cfg(EXAMPLES / "jelly_cube.png", scene="drop", drop_height_m=0.05)
    report = run_pipeline(cfg).report
    run = cfg.output_dir
    check_run_folder(run, report)
    assert report["input"]["kind"] == "photo" and report["input"]["mask_source"] == "alpha"
    # The saved mask is the one used: the photo's alpha > 0.5.
    alpha = np.asarray(Image.open(EXAMPLES / "jelly_cube.png"))[..., 3] > 127
    saved = np.asarray(Image.open(run / "mask.png")) > 127
    assert saved.shape == alpha.shape and (saved == alpha).mean() > 0.999
    # The model ran on the training camera at its input size (32 px here).
    assert report["checkpoint"]["input_size"] == 32 and Image.open(run / "input.png").size == (256, 256)
    phys = json.loads((run / "physics.json").read_text())
    probs = phys["posterior"]["material_probs"]
    assert len(probs) == 15 and sum(probs.values()) == pytest.approx(1.0, abs=1e-3)
    mean = phys["runs"][0]
    assert mean["material"] == max(probs, key=probs.get) and mean["why"]["material"] == "posterior mean"
    # The posterior-mean E, projected onto the predicted material's range when it lies outside.
    from physgm.physics.materials import get_material

    lo, hi = get_material(mean["material"]).E_range
    assert mean["E"] == pytest.approx(min(max(phys["posterior"]["E_Pa"]["mean"], lo), hi), rel=1e-3)
    assert ("projected" in mean["why"]["E"]) == (not lo <= phys["posterior"]["E_Pa"]["mean"] <= hi)
    # Drop: the object starts drop_height above the ground (t = 0 PLY) and ends lower.
    from physgm.gaussians import read_ply

    g0 = read_ply(run / "gaussians.ply")
    assert float(g0.means[g0.opacities >= 0.05][:, 2].min()) == pytest.approx(0.05, abs=0.01)


def test_photo_segmentation_overrides_and_stretch(make_cfg):
    """A JPEG without alpha is segmented; explicit physics wins over the prediction; the stretch
    runs across the line of sight (world y for the canonical camera on the +x axis, or z for a body
    taller than it is wide)."""
    from physgm.gaussians import read_ply

    cfg = make_cfg(
        EXAMPLES / "rubber_blob_plain.jpg",
        scene="stretch",
        physics__material="jelly",
        physics__E=2e5,
        physics__nu=0.4,
        output__frame_plys=True,
    )
    report = run_pipeline(cfg).report
    check_run_folder(cfg.output_dir, report)
    assert report["input"]["mask_source"] == "segmentation"
    phys = json.loads((cfg.output_dir / "physics.json").read_text())
    run = phys["runs"][0]
    assert (run["material"], run["E"], run["nu"]) == ("jelly", 2e5, 0.4)
    assert all(run["why"][k].startswith("override") for k in ("material", "E", "nu"))
    assert report["runs"][0]["material"] == "jelly" and report["scene"] == "stretch"
    assert report["runs"][0]["E_used"] <= 2e5
    first, last = (read_ply(cfg.output_dir / "frames" / f"frame_{t:04d}.ply") for t in (0, 5))
    opaque = first.means[first.opacities >= 0.05].numpy()
    axis = 2 if np.ptp(opaque[:, 2]) > np.ptp(opaque[:, 1]) else 1
    assert report["scene_settings"]["axis"] == axis
    # Grips move apart at 0.25 m/s each for 0.2 s: the 0.2 m object grows towards 0.3 m.
    assert float(np.ptp(last.means[:, axis].numpy())) > 1.2 * float(np.ptp(first.means[:, axis].numpy()))


def test_samples_give_k_videos(make_cfg):
    cfg = make_cfg(EXAMPLES / "metal_can.png", physics__samples=2, output__gif=True)
    report = run_pipeline(cfg).report
    check_run_folder(cfg.output_dir, report, n_videos=3)
    for k in range(2):
        assert video_frames(cfg.output_dir / f"video_sample{k}.mp4") == 6
    assert (cfg.output_dir / "video.gif").is_file()
    phys = json.loads((cfg.output_dir / "physics.json").read_text())
    assert [r["name"] for r in phys["runs"]] == ["mean", "sample0", "sample1"]
    assert [r["video"] for r in phys["runs"]] == ["video.mp4", "video_sample0.mp4", "video_sample1.mp4"]
    # Each sample is its own draw from the posterior, recorded as such.
    assert len({r["E"] for r in phys["runs"]}) == 3
    assert all(r["why"]["E"].startswith(f"posterior sample {k}") for k, r in enumerate(phys["runs"][1:]))
    assert [r["material"] for r in report["runs"]] == [r["material"] for r in phys["runs"]]


def test_views_folder_push(make_cfg):
    cfg = make_cfg(EXAMPLES / "plasticine_views", scene="push", physics__material="rubber")
    report = run_pipeline(cfg).report
    check_run_folder(cfg.output_dir, report)
    assert report["input"]["kind"] == "views" and report["input"]["views"] == 4
    assert report["camera"]["azimuth_deg"] == pytest.approx(0.0, abs=1e-3)
    assert Image.open(cfg.output_dir / "mask.png").size == (4 * 128, 128)


def test_ply_skips_the_model(make_cfg, blob_ply, tmp_path, capsys):
    """The PhysGaussian workflow: no checkpoint needed, the material is given, frame PLYs written;
    the simulation shows its progress bar."""
    from physgm.gaussians import read_ply

    cfg = make_cfg(
        blob_ply,
        ckpt=tmp_path / "absent.ckpt",
        physics__material="rubber",
        output__frame_plys=True,
        output__progress=True,
    )
    report = run_pipeline(cfg).report
    bar = f"mean: simulating ({report['mode']}, {report['particles']:,} particles)"
    assert bar in capsys.readouterr().err
    check_run_folder(cfg.output_dir, report)
    assert report["input"]["kind"] == "ply" and report["checkpoint"] is None
    phys = json.loads((cfg.output_dir / "physics.json").read_text())
    assert phys["posterior"] is None and phys["runs"][0]["why"]["E"].startswith("material table default")
    plys = sorted((cfg.output_dir / "frames").glob("frame_*.ply"))
    assert len(plys) == 6
    first, last = read_ply(plys[0]), read_ply(plys[-1])
    assert len(first) == len(last) == 600
    # The object fell: the last frame is lower than the first.
    assert float(last.means[:, 2].mean()) < float(first.means[:, 2].mean()) - 0.01


def test_greyscale_16bit_photo_with_mask_file(make_cfg, tmp_path):
    """A 16-bit greyscale PNG of any size with the object given by a mask file."""
    yy, xx = np.mgrid[:90, :140]
    inside = ((yy - 50) / 25.0) ** 2 + ((xx - 60) / 35.0) ** 2 < 1
    grey = np.where(inside, 20000 + 100 * xx, 60000).astype(np.uint16)
    photo = tmp_path / "grey16.png"
    Image.fromarray(grey).save(photo)
    assert Image.open(photo).mode.startswith("I;16")
    mask = tmp_path / "mask_in.png"
    Image.fromarray((inside * 255).astype(np.uint8)).save(mask)
    cfg = make_cfg(photo, mask=mask, physics__material="wood")
    report = run_pipeline(cfg).report
    check_run_folder(cfg.output_dir, report)
    assert report["input"]["mask_source"] == "mask file" and report["input"]["size"] == [140, 90]
    saved = np.asarray(Image.open(cfg.output_dir / "mask.png")) > 127
    assert (saved == inside).all()
    # The model saw the grey object framed like the training renders, as RGB.
    seen = np.asarray(Image.open(cfg.output_dir / "input.png")).astype(int)
    assert seen.shape == (256, 256, 3) and np.abs(seen[..., 0] - seen[..., 2]).max() <= 1


@pytest.mark.slow
def test_default_settings_full_clip(make_cfg):
    """The defaults (256 px, 50 frames at 25 fps) on a shipped example: a complete, finite clip."""
    from physgm.pipeline.config import OutputSettings

    cfg = make_cfg(EXAMPLES / "wood_toy_cluttered.jpg", output=OutputSettings(progress=False))
    report = run_pipeline(cfg).report
    assert (report["output"]["resolution"], report["output"]["frames"], report["output"]["fps"]) == (
        256,
        50,
        25.0,
    )
    assert video_frames(cfg.output_dir / "video.mp4") == 50 and report["finite"] is True


def test_shipped_checkpoint_runs_every_shipped_photo(make_cfg):
    """The checkpoint in the repository loads, fits the size budget, records its recipe, and simulates."""
    import torch

    from physgm import CHECKPOINT_FORMAT_VERSION
    from physgm.model.checkpoint import REPO_ROOT, input_size, load_model
    from physgm.physics.behaviour import MATERIAL_BEHAVIOUR

    path = REPO_ROOT / "checkpoints" / "physgm_tiny.ckpt"
    assert path.stat().st_size <= 25 * 2**20
    raw = torch.load(path, map_location="cpu", weights_only=False)
    assert raw["hyper_parameters"]["format_version"] == CHECKPOINT_FORMAT_VERSION
    assert "experiment=cpu_frozen" in raw["physgm"]["recipe"]
    model, ckpt = load_model(path)
    assert input_size(model, ckpt.hparams) == 128 and model.config.physics_head.semantic_prior_weight > 0
    synthetic = ("jelly_cube.png", "metal_can.png", "rubber_blob_plain.jpg", "wood_toy_cluttered.jpg")
    real = ("ceramic_mug.png", "basketball.png", "soda_can.png")
    labels = json.loads((EXAMPLES / "labels.json").read_text())
    gates = {}
    for photo in synthetic + real:
        cfg = make_cfg(EXAMPLES / photo, ckpt=path)
        cfg.output_dir = cfg.output_dir.with_name(f"run_{Path(photo).stem}")
        report = run_pipeline(cfg).report
        check_run_folder(cfg.output_dir, report)
        assert report["checkpoint"]["input_size"] == 128
        physics = json.loads((cfg.output_dir / "physics.json").read_text())
        gates[photo] = physics["posterior"]["domain_real"]
        # what the viewer sees is the labelled behaviour class, for real objects and procedural ones
        simulated = physics["runs"][0]["material"]
        assert MATERIAL_BEHAVIOUR[simulated] == MATERIAL_BEHAVIOUR[labels[photo]], (photo, simulated)
    # the shipped file's domain gate weighs the semantic prior in for renders of real meshes far
    # more than for procedural ones (0.56-0.83 against 0.01-0.05 in the file of 4 December 2026, with
    # the photos' alpha composited as in training)
    assert min(gates[p] for p in real) > 0.3 and max(gates[p] for p in synthetic) < 0.1, gates
