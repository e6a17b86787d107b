"""Speed-against-error sweep: run summaries, the table and plot, and a real two-job Hydra multirun."""

import csv
import json
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import torch

from physgm.model.config import PhysGMConfig
from physgm.model.physgm import PhysGM
from physgm.train.sweep import write_run_summary, write_table

ROOT = Path(__file__).resolve().parents[2]


def small_model() -> PhysGM:
    cfg = PhysGMConfig.from_dict(
        {
            "backbone": {
                "encoder": {"img_size": 16, "depth": 1},
                "depth": 4,
                "width": 64,
                "out_layers": [0, 1, 2, 3],
            }
        }
    )
    return PhysGM(cfg, load_pretrained=False)


def test_run_summary_counts_parameters_and_times_the_forward(tmp_path):
    model = small_model()
    path = write_run_summary(
        tmp_path, model, {"val/v4/psnr": 20.5, "train/loss": 1.0}, steps=7, overrides=["a=1"], repeats=2
    )
    s = json.loads(path.read_text())
    assert s["parameters"] == sum(p.numel() for p in model.parameters())
    assert s["input_resolution"] == 16 and s["steps"] == 7 and s["overrides"] == "a=1"
    assert s["val/v4/psnr"] == 20.5 and "train/loss" not in s
    lo, hi = s["forward_ms_spread"]
    assert 0 < lo <= s["forward_ms"] <= hi
    assert torch.get_num_threads() >= 1 and model.training  # the timing restores the mode


def test_table_orders_runs_by_speed_and_draws_the_plot(tmp_path):
    for i, (ms, psnr) in enumerate([(30.0, 24.0), (10.0, 21.0), (90.0, 26.5)]):
        (tmp_path / str(i)).mkdir()
        (tmp_path / str(i) / "summary.json").write_text(
            json.dumps(
                {
                    "overrides": f"w={i}",
                    "parameters": 1_000_000 * (i + 1),
                    "input_resolution": 64,
                    "forward_ms": ms,
                    "steps": 10,
                    "val/v4/psnr": psnr,
                    "val/v1/psnr": psnr - 3,
                    "val/v4/material_acc": 0.5,
                }
            )
        )
    paths = write_table(tmp_path)
    rows = list(csv.DictReader(open(paths["csv"])))
    assert [float(r["forward_ms"]) for r in rows] == [10.0, 30.0, 90.0]
    assert [r["val/v4/psnr"] for r in rows] == ["21.0", "24.0", "26.5"]
    assert len(paths["md"].read_text().strip().splitlines()) == 2 + 3
    assert iio.imread(paths["png"]).ndim == 3


def test_hydra_multirun_writes_one_row_per_job(tiny_dataset, tmp_path):
    sweep = tmp_path / "sweep"
    cmd = [
        sys.executable,
        str(ROOT / "train.py"),
        "-m",
        "experiment=sweep_cpu",
        "synth=null",
        f"data.root={tiny_dataset}",
        "data.val_split=train",
        "data.num_workers=0",
        "data.batch_size=2",
        "data.target_resolution=32",
        "data.num_targets=5",
        "+trainer.fast_dev_run=1",
        "torch_threads=1",
        "model.backbone.width=64,128",
        "data.input_resolution=32",  # these replace the config's grid
        f"hydra.sweep.dir={sweep}",
        "callbacks.progress_bar=null",
    ]
    done = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=480)
    assert done.returncode == 0, done.stderr[-3000:]
    rows = list(csv.DictReader(open(sweep / "sweep.csv")))
    assert sorted(r["overrides"].split()[0] for r in rows) == [
        "model.backbone.width=128",
        "model.backbone.width=64",
    ]
    assert all(r["input_resolution"] == "32" for r in rows)
    assert (sweep / "sweep.png").is_file()
