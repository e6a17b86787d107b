"""The synthetic generator: same seed same bytes, resumable, atomic, consistent labels."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from physgm.data.annotation import E_CATEGORIES
from physgm.data.format import SPLITS, load_asset, read_split
from physgm.data.synth import asset_id, generate, main, plan_asset
from physgm.data.writer import TMP_PREFIX


def _digest(root) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_same_seed_same_bytes_other_seed_other_bytes(tmp_path, make_config):
    cfg = make_config(3, seed=11)
    generate(cfg, tmp_path / "a", progress=False)
    generate(cfg, tmp_path / "b", progress=False)
    a, b = _digest(tmp_path / "a"), _digest(tmp_path / "b")
    assert a == b and len(a) == 3 * 35 + 5  # per asset 32 views + 2 json + ply; synth.json + 4 splits
    generate(make_config(3, seed=12), tmp_path / "c", progress=False)
    c = _digest(tmp_path / "c")
    assert a["syn_000000/rgba/000.png"] != c["syn_000000/rgba/000.png"]


def test_assets_with_reference_videos_are_deterministic_too(tmp_path, make_config):
    cfg = make_config(1, seed=5, gaussians=400, video_fraction=1.0)
    generate(cfg, tmp_path / "a", progress=False)
    generate(cfg, tmp_path / "b", progress=False)
    a = _digest(tmp_path / "a")
    assert "syn_000000/videos/drop.mp4" in a and "syn_000000/videos/drop.json" in a
    assert a == _digest(tmp_path / "b")
    assert read_split(tmp_path / "a", plan_asset(cfg, 0).split) == ["syn_000000"]
    assert plan_asset(cfg, 0).split in ("dpo", "test")


def test_worker_processes_give_the_same_bytes(tmp_path, make_config):
    cfg = make_config(2, seed=11)
    generate(cfg, tmp_path / "one", workers=1, progress=False)
    generate(cfg, tmp_path / "two", workers=2, progress=False)
    assert _digest(tmp_path / "one") == _digest(tmp_path / "two")


def test_resume_skips_finished_assets_and_redoes_interrupted_ones(tiny_copy, make_config):
    root = tiny_copy
    before = _digest(root)
    shutil.rmtree(root / "syn_000005")  # as if the run had stopped before this asset was renamed
    (root / f"{TMP_PREFIX}syn_000005" / "rgba").mkdir(parents=True)  # its half-written temp folder
    summary = generate(make_config(24, seed=3), root, progress=False)
    assert summary["done"] == 1 and summary["skipped"] == 23
    assert not list(root.glob(f"{TMP_PREFIX}*"))
    assert _digest(root) == before


def test_resume_with_other_settings_is_refused(tiny_copy, make_config):
    with pytest.raises(SystemExit, match="resolution"):
        generate(make_config(24, seed=3, resolution=48), tiny_copy, progress=False)


def test_without_the_gaussians_file_the_rest_is_the_same_bytes(tmp_path, make_config):
    generate(make_config(2, seed=11), tmp_path / "with", progress=False)
    generate(make_config(2, seed=11, gaussians_file=False), tmp_path / "without", progress=False)
    a, b = _digest(tmp_path / "with"), _digest(tmp_path / "without")
    plys = {k for k in a if k.endswith("gaussians.ply")}
    assert len(plys) == 2 and not any(k.endswith("gaussians.ply") for k in b)
    assert {k: v for k, v in a.items() if k not in plys | {"synth.json"}} == {
        k: v for k, v in b.items() if k != "synth.json"
    }
    assert load_asset(tmp_path / "without" / "syn_000000").gaussians_path is None


def test_a_set_made_before_the_gaussians_file_setting_resumes(tiny_copy, make_config):
    path = tiny_copy / "synth.json"
    stored = json.loads(path.read_text())
    assert stored.pop("gaussians_file") is True
    path.write_text(json.dumps(stored))
    assert generate(make_config(24, seed=3), tiny_copy, progress=False)["skipped"] == 24
    with pytest.raises(SystemExit, match="gaussians_file"):
        generate(make_config(24, seed=3, gaussians_file=False), tiny_copy, progress=False)


def test_assets_load_and_labels_are_consistent(tiny_root):
    ids = [i for s in SPLITS for i in read_split(tiny_root, s)]
    assert sorted(ids) == [asset_id(i) for i in range(24)]  # every asset in exactly one split
    for aid in ids[:6]:
        asset = load_asset(tiny_root / aid)
        phys = json.loads((asset.path / "physical.json").read_text())
        assert len(asset) == 32 and asset.cameras.width == 32
        assert asset.physical.true_known and asset.physical.annotation.E in E_CATEGORIES
        assert phys["material"] == plan_asset_from(tiny_root, aid).material
        rgba = asset.load_rgba([0, 31])
        assert rgba.shape == (2, 32, 32, 4) and rgba[..., 3].max() > 0.5
        # The canonical view 0 looks along -x from azimuth 0, elevation 0, 1.8 m away.
        np.testing.assert_allclose(asset.cameras.c2w[0, :3, 3].numpy(), [1.8, 0.0, 0.0], atol=1e-6)
        assert asset.azimuth_deg[8] == 0.0 and asset.elevation_deg[8] == 20.0
        assert len(asset.load_gaussians()) == 600


def plan_asset_from(root, aid):
    from physgm.data.synth import SynthConfig

    cfg = json.loads((root / "synth.json").read_text())
    cfg.pop("generator_version")
    return plan_asset(SynthConfig(**cfg), int(aid.split("_")[1]))


def test_cli_prints_throughput_and_json(tmp_path, capsys):
    code = main(
        [
            "--out",
            str(tmp_path / "cli"),
            "--count",
            "2",
            "--resolution",
            "32",
            "--gaussians",
            "300",
            "--video-fraction",
            "0",
            "--no-progress",
            "--label-noise",
            "0.3",
            "--no-gaussians-file",
        ]
    )
    out = capsys.readouterr().out.strip().splitlines()
    assert code == 0 and "assets/min" in out[0]
    summary = json.loads(out[1])
    assert summary["done"] == 2 and summary["assets_per_min"] > 0
    stored = json.loads((tmp_path / "cli" / "synth.json").read_text())
    assert stored["annotator"]["p_neighbour_E"] == 0.3
    assert stored["gaussians_file"] is False and not list((tmp_path / "cli").glob("*/gaussians.ply"))


def test_plan_split_fractions_follow_config(make_config):
    cfg = make_config(4000, seed=0, video_fraction=0.25)
    plans = [plan_asset(cfg, i) for i in range(cfg.count)]
    video = np.mean([p.video for p in plans])
    assert abs(video - 0.25) < 4 * np.sqrt(0.25 * 0.75 / cfg.count)
    assert all(p.split in ("dpo", "test") for p in plans if p.video)
    assert all(p.split in ("train", "val", "test") for p in plans if not p.video)
    assert len({p.material for p in plans}) == 15 and len({p.family for p in plans}) >= 10


_BUSY_POOL = """
import multiprocessing as mp, os, sys, time
from physgm.data import synth
if __name__ == "__main__":
    pool = mp.get_context("spawn").Pool(2, initializer=synth._pool_worker_init)
    pool.map(time.sleep, [0.5, 0.5])  # both workers up
    for _ in range(2):
        pool.apply_async(time.sleep, (60,))  # busy, as on an asset, when the parent dies
    time.sleep(1.0)
    print(" ".join(str(p.pid) for p in mp.active_children()), flush=True)
    time.sleep(120)
"""


def _running(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has exited
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_pool_workers_stop_when_the_generating_process_is_killed(tmp_path):
    script = tmp_path / "busy_pool.py"
    script.write_text(_BUSY_POOL)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[2] / "src")}
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        workers = [int(p) for p in proc.stdout.readline().split()]
        assert len(workers) == 2 and all(_running(w) for w in workers)
        proc.kill()
        proc.wait()
        deadline = time.monotonic() + 10.0  # the workers' tasks would run for another minute
        while any(_running(w) for w in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(_running(w) for w in workers)
    finally:
        proc.kill()
