"""The render benchmark prints one JSON report (slow: it times the torch reference)."""

from __future__ import annotations

import json

import pytest

from physgm.bench import render_speed as bench


def test_bench_scene_is_an_object_in_front_of_the_camera():
    scene = bench.make_scene(512, 32)
    assert scene["means"].norm(dim=-1).max() <= 0.5
    cam_z = (scene["viewmats"][0, :3, :3] @ scene["means"].T + scene["viewmats"][0, :3, 3:]).T[:, 2]
    assert 1.2 < float(cam_z.min()) and float(cam_z.max()) < 2.4  # seen from 1.8 m
    assert 0.01 <= float(scene["scales"].min()) and float(scene["scales"].max()) <= 0.03


@pytest.mark.slow
def test_bench_prints_one_json_object(capsys):
    report = bench.main(["--repeats", "1"])
    printed = json.loads(capsys.readouterr().out)
    assert printed == report
    assert {(c["backend"], c["n"], c["res"]) for c in report["cases"]} == {
        (b, n, r) for b in ("torch", "warp") for n, r in bench.SIZES
    }
    for case in report["cases"]:
        assert case["max_abs_diff_vs_torch"] <= 1e-4
    assert set(report["speedup_vs_torch"]) == {"4096x64", "16384x128"}
