"""Bad input stops with one ``error: ...`` line, exit code 2 and no run folder; failures are atomic."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]


def compose(overrides: list[str]):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return hydra_compose("simulate", overrides=overrides)


def run_expect_error(capsys, tmp_path, overrides: list[str]) -> str:
    """Run through the Hydra entry; return the one error line after checking exit code and leftovers."""
    from physgm.pipeline import run

    out = tmp_path / "out" / "run"
    base = ["output.resolution=32", "output.frames=4", "output.progress=false", f"paths.output_dir={out}"]
    with pytest.raises(SystemExit) as exc:
        run(compose(base + overrides))
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "Traceback" not in err
    leftovers = list(out.parent.iterdir()) if out.parent.exists() else []
    assert leftovers == [], f"partial outputs left behind: {leftovers}"
    return err


def test_missing_file(capsys, tmp_path, tiny_ckpt):
    err = run_expect_error(capsys, tmp_path, [f"input={tmp_path / 'nope.png'}", f"ckpt={tiny_ckpt}"])
    assert "input not found" in err and "nope.png" in err


def test_not_an_image(capsys, tmp_path, tiny_ckpt):
    fake = tmp_path / "notes.png"
    fake.write_text("this is text, not a PNG\n")
    err = run_expect_error(capsys, tmp_path, [f"input={fake}", f"ckpt={tiny_ckpt}"])
    assert "not an image" in err


def test_truncated_png(capsys, tmp_path, tiny_ckpt, examples):
    data = (examples / "jelly_cube.png").read_bytes()
    cut = tmp_path / "cut.png"
    cut.write_bytes(data[: len(data) // 2])
    err = run_expect_error(capsys, tmp_path, [f"input={cut}", f"ckpt={tiny_ckpt}"])
    assert "truncated" in err


def test_absurd_size(capsys, tmp_path, tiny_ckpt, png_with_size_header):
    big = png_with_size_header(tmp_path / "huge.png", 20000, 20000)
    err = run_expect_error(capsys, tmp_path, [f"input={big}", f"ckpt={tiny_ckpt}"])
    assert "20000 x 20000" in err and "Resize" in err


@pytest.mark.parametrize("how", ["mask file", "transparent"])
def test_empty_mask(capsys, tmp_path, tiny_ckpt, rgba_png, examples, how):
    if how == "mask file":
        black = rgba_png(tmp_path / "black.png", alpha_value=255, disc=False)
        from PIL import Image

        Image.new("L", (256, 256), 0).save(black)
        args = [f"input={examples / 'jelly_cube.png'}", f"mask={black}"]
    else:
        args = [f"input={rgba_png(tmp_path / 'clear.png', alpha_value=0)}"]
    err = run_expect_error(capsys, tmp_path, [*args, f"ckpt={tiny_ckpt}"])
    assert "no object found" in err


def test_unwritable_output(capsys, tmp_path, tiny_ckpt, examples):
    from physgm.pipeline import run

    blocker = tmp_path / "file"
    blocker.write_text("a file where the parent folder should be")
    cfg = compose(
        [f"input={examples / 'jelly_cube.png'}", f"ckpt={tiny_ckpt}", f"paths.output_dir={blocker / 'run'}"]
    )
    with pytest.raises(SystemExit) as exc:
        run(cfg)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: cannot write the run folder") and "paths.output_dir" in err
    assert blocker.read_text().startswith("a file")


def test_existing_output_folder_is_not_overwritten(capsys, tmp_path, tiny_ckpt, examples):
    from physgm.pipeline import run

    out = tmp_path / "done"
    out.mkdir()
    (out / "video.mp4").write_bytes(b"earlier run")
    with pytest.raises(SystemExit):
        run(compose([f"input={examples / 'jelly_cube.png'}", f"ckpt={tiny_ckpt}", f"paths.output_dir={out}"]))
    assert "already exists and is not empty" in capsys.readouterr().err
    assert (out / "video.mp4").read_bytes() == b"earlier run"


def _edited_checkpoint(src: Path, dst: Path, edit) -> Path:
    ckpt = torch.load(src, weights_only=False)
    edit(ckpt)
    torch.save(ckpt, dst)
    return dst


def _shape_change(ckpt):
    key = next(k for k, v in ckpt["state_dict"].items() if v.ndim == 2)
    ckpt["state_dict"][key] = torch.zeros(3, 3)


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (lambda c: c["hyper_parameters"].update(format_version=2), "format version 2"),
        (
            lambda c: c["hyper_parameters"]["model"]["backbone"].update(rotary=True),
            "incompatible physgm version",
        ),
        (_shape_change, "wrong shape"),
        (lambda c: c["state_dict"].pop(next(iter(c["state_dict"]))), "weights missing"),
        (lambda c: c["state_dict"].update({"model.extra.weight": torch.zeros(1)}), "unknown weights"),
        (lambda c: c.pop("hyper_parameters"), "not a physgm checkpoint"),
    ],
    ids=["format-version", "config-key", "shape", "missing-key", "extra-key", "no-hparams"],
)
def test_incompatible_checkpoint(capsys, tmp_path, tiny_ckpt, examples, edit, expected):
    bad = _edited_checkpoint(tiny_ckpt, tmp_path / "bad.ckpt", edit)
    err = run_expect_error(capsys, tmp_path, [f"input={examples / 'jelly_cube.png'}", f"ckpt={bad}"])
    assert expected in err


def test_missing_and_corrupt_checkpoint(capsys, tmp_path, examples):
    err = run_expect_error(
        capsys, tmp_path, [f"input={examples / 'jelly_cube.png'}", f"ckpt={tmp_path / 'none.ckpt'}"]
    )
    assert "python train.py experiment=tiny_cpu" in err and "ckpt=" in err
    junk = tmp_path / "junk.ckpt"
    junk.write_bytes(b"\x00not a checkpoint" * 10)
    err = run_expect_error(capsys, tmp_path, [f"input={examples / 'jelly_cube.png'}", f"ckpt={junk}"])
    assert "not a readable PyTorch checkpoint" in err


def test_bad_settings(capsys, tmp_path, tiny_ckpt, examples, blob_ply):
    photo = f"input={examples / 'jelly_cube.png'}"
    assert "ply input has no predicted physics" in run_expect_error(capsys, tmp_path, [f"input={blob_ply}"])
    assert "physics.material='lava'" in run_expect_error(capsys, tmp_path, [photo, "physics.material=lava"])
    assert "scene='swirl'" in run_expect_error(capsys, tmp_path, [photo, "scene=swirl"])
    err = run_expect_error(capsys, tmp_path, [photo, f"ckpt={tiny_ckpt}", "+scene_overrides.wobble=1"])
    assert "no setting(s) ['wobble']" in err
    # A value the scene refuses stops the run before the checkpoint is read (it does not exist).
    missing = f"ckpt={tmp_path / 'none.ckpt'}"
    err = run_expect_error(capsys, tmp_path, [photo, missing, "scene=stretch", "+scene_overrides.grip=glue"])
    assert "scene 'stretch': stretch grip must be slip or clamp, got 'glue'" in err
    err = run_expect_error(capsys, tmp_path, [photo, missing, "scene=stretch", "+scene_overrides.ratio=0.5"])
    assert "ratio > 1" in err
    # So does a mistyped planner setting.
    err = run_expect_error(capsys, tmp_path, [photo, missing, "+planner.min_opacty=0.1"])
    assert "bad planner settings" in err and "min_opacty" in err
    assert "physics.nu=0.7" in run_expect_error(capsys, tmp_path, [photo, "physics.nu=0.7"])
    assert "input is required" in run_expect_error(capsys, tmp_path, [])


def test_a_stretch_the_material_does_not_survive_stops_before_simulating(capsys, tmp_path, blob_ply):
    """Fracture is not modelled: a ceramic pulled to twice its length is refused, with what to do."""
    err = run_expect_error(
        capsys, tmp_path, [f"input={blob_ply}", "physics.material=ceramic", "scene=stretch"]
    )
    assert (
        "cannot simulate mean: ceramic" in err
        and "real ceramic fails in tension at about 0.002 strain" in err
    )
    assert "Stretch it less" in err


def test_a_run_predicted_past_max_sim_minutes_stops_before_simulating(
    capsys, tmp_path, blob_ply, monkeypatch
):
    """A 5 mm metal blob drawn 20 % at steel's stiffness: 1.4 million sub-steps a frame (its step
    follows steel's wave speed across a 0.4 mm cell), half an hour even at the guard's throughput,
    so the run stops after planning with the prediction and the ways out."""
    import physgm.sim.gaussian_trajectory as gt

    def no_simulation(*args, **kwargs):
        raise AssertionError("the guard let the run start")

    monkeypatch.setattr(gt, "run_prepared", no_simulation)
    drawn = [f"input={blob_ply}", "physics.material=metal", "scene=stretch", "+scene_overrides.ratio=1.2"]
    err = run_expect_error(capsys, tmp_path, [*drawn, "object.size=0.005"])
    took = re.search(r"would take ([\d.]+) (minutes|hours) or more, over max_sim_minutes=10 ", err)
    assert took and float(took[1]) * (60 if took[2] == "hours" else 1) > 10, err
    assert (
        "mean: metal" in err and "sub-steps a frame" in err and "max_sim_minutes=null runs it anyway" in err
    )
    assert "max_sim_minutes=-1" in run_expect_error(capsys, tmp_path, [*drawn, "max_sim_minutes=-1"])


def test_a_diverged_simulation_is_one_error_line(capsys, tmp_path, blob_ply, monkeypatch):
    """When the divergence guard gives up, the user gets its reason and the settings to change."""
    import physgm.sim.gaussian_trajectory as gt
    from physgm.sim.mpm.stepping import SimulationDiverged

    def diverge(*args, **kwargs):
        raise SimulationDiverged("MPM diverged in frame 0 (t=0 s): 2 particles reached a non-finite state.")

    monkeypatch.setattr(gt, "run_prepared", diverge)
    err = run_expect_error(capsys, tmp_path, [f"input={blob_ply}", "physics.material=jelly"])
    assert "the simulation of mean: jelly" in err and "MPM diverged in frame 0" in err
    assert "solver.cfl=0.2" in err


def test_failure_mid_run_leaves_nothing(tmp_path, make_cfg, examples, monkeypatch):
    """An error after the videos were written removes everything, including an empty run folder
    made beforehand (as Hydra does)."""
    import physgm.pipeline.stages as pipeline_run
    from physgm.pipeline import run_pipeline

    real = pipeline_run.write_json

    def failing(path, data):
        if path.name == "report.json":
            raise OSError("disk full")
        real(path, data)

    monkeypatch.setattr(pipeline_run, "write_json", failing)
    cfg = make_cfg(examples / "metal_can.png", physics__material="metal")
    cfg.output_dir.mkdir()
    with pytest.raises(OSError, match="disk full"):
        run_pipeline(cfg)
    assert list(cfg.output_dir.parent.iterdir()) == [], "no run folder and no temporary folder may remain"


def test_non_finite_simulation_writes_nothing(tmp_path, make_cfg, examples, monkeypatch):
    import physgm.render.frames as render_frames
    from physgm.pipeline import run_pipeline

    real = render_frames.render_trajectory

    def poisoned(traj, *args, **kwargs):
        traj.x[-1, 0, 0] = float("nan")  # as if the solver had diverged
        return real(traj, *args, **kwargs)

    monkeypatch.setattr(render_frames, "render_trajectory", poisoned)
    cfg = make_cfg(examples / "metal_can.png", physics__material="rubber")
    with pytest.raises(RuntimeError, match="non-finite"):
        run_pipeline(cfg)
    assert not cfg.output_dir.exists() and list(cfg.output_dir.parent.iterdir()) == []


def test_cli(tmp_path, blob_ply):
    """simulate.py through Hydra: a user error exits 2 with one line; a good run fills the run folder."""
    out = tmp_path / "cli"
    base = [
        sys.executable,
        str(ROOT / "simulate.py"),
        "output.resolution=32",
        "output.frames=4",
        "output.progress=false",
    ]
    bad = subprocess.run(
        [*base, f"input={tmp_path / 'missing.jpg'}", f"paths.output_dir={out}"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert bad.returncode == 2
    assert (
        bad.stderr.strip().splitlines()[-1].startswith("error: input not found")
        and "Traceback" not in bad.stderr
    )
    assert not out.exists()
    good = subprocess.run(
        [*base, f"input={blob_ply}", "physics.material=metal", "scene=push", f"paths.output_dir={out}"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert good.returncode == 0, good.stderr[-2000:]
    assert {"video.mp4", "report.json", "physics.json", "contact_sheet.png", "gaussians.ply"} <= {
        p.name for p in out.iterdir()
    }
    assert list(tmp_path.glob(".cli.tmp-*")) == []
