"""The three commands the project exists for, typed as the mission writes them, end without a traceback.

    python train.py stage=pretrain
    python train.py stage=dpo
    python simulate.py input=img.png

Each runs as a user's subprocess from the repository root, with only ``+trainer.fast_dev_run=true``
(training) or fewer frames (simulation) and a tiny data recipe added, so it takes a minute or two on
a 2-core CPU. The defaults do the rest: stage 1 generates its data set (the default recipe, made tiny
here by ``synth.*`` overrides), stage 2 starts from the shipped ``checkpoints/physgm_tiny.ckpt``.
"""

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# The default recipe at test size: 6 assets of 32 px, half with a reference drop video (the dpo split).
TINY_SYNTH = [
    "synth.count=6",
    "synth.resolution=32",
    "synth.gaussians=400",
    "synth.video_fraction=0.5",
    "synth.workers=1",
]


def assert_clean(done: subprocess.CompletedProcess) -> None:
    assert "Traceback" not in done.stderr + done.stdout, done.stderr[-5000:]
    assert done.returncode == 0, done.stderr[-5000:]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("mission") / "data"


def test_train_stage_pretrain_generates_its_data_and_trains(data_dir, tmp_path, run_python):
    done = run_python(
        "train.py",
        "stage=pretrain",
        "+trainer.fast_dev_run=true",
        f"paths.data_dir={data_dir}",
        *TINY_SYNTH,
        "data.val_split=train",
        "data.num_workers=0",
        f"paths.output_dir={tmp_path / 'run'}",
    )
    assert_clean(done)
    assert (
        (data_dir / "synthetic" / "splits" / "train.txt").read_text().split()
    )  # the default data set was made
    assert "generating the synthetic data set" in done.stderr + done.stdout


def test_train_stage_pretrain_without_data_or_recipe_says_what_to_add(tmp_path, run_python):
    done = run_python(
        "train.py",
        "stage=pretrain",
        "synth=null",
        f"paths.data_dir={tmp_path / 'none'}",
        f"paths.output_dir={tmp_path / 'run'}",
    )
    assert done.returncode != 0 and "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert lines[-1].startswith(f"error: no data set at {tmp_path / 'none' / 'synthetic'}"), done.stderr[
        -3000:
    ]
    assert "experiment=tiny_cpu" in lines[-1]
    assert not (tmp_path / "none").exists()


def test_train_stage_dpo_starts_from_the_shipped_checkpoint(data_dir, tmp_path, run_python):
    if not (data_dir / "synthetic" / "splits" / "dpo.txt").is_file():
        pytest.skip("needs the data set made by the stage=pretrain test")
    done = run_python(
        "train.py",
        "stage=dpo",
        "+trainer.fast_dev_run=true",
        f"paths.data_dir={data_dir}",
        *TINY_SYNTH,
        "stage.rollout.batch_size=1",
        "stage.rollout.num_candidates=2",
        "stage.rollout.workers=1",
        "stage.rollout.sim.resolution=32",
        "stage.rollout.sim.n_frames=8",
        f"paths.output_dir={tmp_path / 'run'}",
    )
    assert_clean(done)
    rounds = list((tmp_path / "run" / "pairs").glob("round_0000/*.json"))
    assert rounds, "no rollout was cached"


def test_train_stage_dpo_without_a_checkpoint_says_what_to_add(tmp_path, run_python):
    done = run_python(
        "train.py", "stage=dpo", "stage.init_ckpt=missing.ckpt", f"paths.output_dir={tmp_path / 'run'}"
    )
    assert done.returncode != 0 and "Traceback" not in done.stderr
    assert (
        done.stderr.strip().splitlines()[-1].startswith("error: stage.init_ckpt=missing.ckpt is not a file")
    )


def test_simulate_input_img_png(tmp_path, run_python):
    shutil.copy(ROOT / "examples" / "jelly_cube.png", tmp_path / "img.png")
    out = tmp_path / "run"
    done = run_python(
        "simulate.py",
        f"input={tmp_path / 'img.png'}",
        "output.frames=6",
        "output.resolution=64",
        f"paths.output_dir={out}",
    )
    assert_clean(done)
    assert (out / "video.mp4").is_file() and (out / "report.json").is_file()
