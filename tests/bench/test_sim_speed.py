"""``bench sim`` throughput rows: both stepping paths are timed and reported (no timing asserted)."""

from __future__ import annotations

from physgm.bench.sim_speed import throughput


def test_throughput_rows_time_the_python_sub_steps_and_the_frame_path():
    rows = throughput([600], substeps=4, device="cpu", repeats=2)
    assert [r["threads"] for r in rows] == [1, 2]
    for r in rows:
        assert r["particles"] > 500 and r["repeats"] == 2
        assert 0 < r["particle_substeps_per_s_min"] <= r["particle_substeps_per_s"]
        assert r["particle_substeps_per_s"] <= r["particle_substeps_per_s_max"]
        assert r["frames_particle_substeps_per_s"] > 0
