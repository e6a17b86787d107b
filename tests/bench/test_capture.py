"""``python -m physgm.bench capture``: simulate.py on a capture-sized blob, one child process a size."""

from __future__ import annotations

import pytest
import torch

from physgm.bench import capture


def test_the_blob_fills_its_ellipsoid_and_is_the_same_each_time():
    g = capture.capture_blob(4000)
    inside = (((g.means - torch.tensor([0.0, 0.0, 0.3])) / torch.tensor([0.08, 0.06, 0.07])) ** 2).sum(-1)
    assert inside.max() <= 1.0 + 1e-5 and inside.median() > 0.5  # filled, not a shell or a point
    assert torch.allclose(g.quats.norm(dim=-1), torch.ones(4000))
    assert torch.equal(capture.capture_blob(4000).means, g.means)


def test_each_size_runs_the_pipeline_in_its_own_process(tmp_path):
    result = capture.main(["--gaussians", "1500", "--frames", "3", "--res", "32", "--out", str(tmp_path)])
    (row,) = result["runs"]
    assert (row["gaussians"], row["material"], row["mode"]) == (1500, "jelly", "mpm")
    assert row["particles"] > 0 and row["npz_mb"] > 0  # three frames: still falling, in closed form
    assert {"plan", "simulate", "render", "write", "total"} <= set(row["seconds"])
    assert 0.2 < row["peak_rss_gb"] < 8  # the child's own peak, in GB
    assert (tmp_path / "run_1500" / "video.mp4").is_file()


@pytest.mark.parametrize(
    ("args", "message"), [(["--gaussians", "0"], "positive"), (["--material", "cheese"], "unknown")]
)
def test_bad_arguments_stop_before_any_run(args, message, capsys):
    with pytest.raises(SystemExit):
        capture.main(args)
    assert message in capsys.readouterr().err
