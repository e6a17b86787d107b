"""The hull benchmark runs on a data set and reports both searches on the same batches."""

from __future__ import annotations

import json

import pytest

from physgm.bench import hull_speed
from physgm.errors import UserError


def test_report_times_both_searches_on_the_same_batches(tiny_dataset, capsys):
    report = hull_speed.main(
        [
            "--data",
            str(tiny_dataset),
            "--split",
            "test",
            "--assets",
            "4",
            "--resolution",
            "32",
            "--repeats",
            "2",
        ]
    )
    assert json.loads(capsys.readouterr().out) == report
    assert report["batches"] >= 1 and report["views"] == 4 and 0 < report["mask_cover"] < 1
    for name in ("warp", "torch"):
        low, high = report[f"{name}_ms_range"]
        assert 0 < low <= report[f"{name}_ms_median"] <= high
    assert report["rays_differing_max_share"] < 0.01


def test_a_missing_folder_is_a_clear_error(tmp_path):
    with pytest.raises(UserError, match="physgm.data.synth"):
        hull_speed.main(["--data", str(tmp_path / "nowhere")])
