"""``bench sim --only kernels``: the per-kernel report and the bytes it charges each kernel."""

from __future__ import annotations

import warp as wp

from physgm.bench.sim_kernels import kernel_shares


def test_kernel_report_charges_each_particle_kernel_its_arguments_bytes():
    """p2g reads x, v, C (mat33), stress (mat33), mass, vol0, material: 12 + 12 + 36 + 36 + 3 x 4 =
    108 bytes; g2p reads x, v, C, F - I, plastic, escaped, material, vol0, mass (116) and writes
    x, v, C, F - I, stress, plastic (136)."""
    wp.config.log_level = wp.LOG_WARNING
    report = kernel_shares(n=4_000, repeats=2)
    rows = {row["kernel"]: row for row in report["kernels"]}
    assert set(rows) == {"p2g", "grid_update", "g2p", "substep"}
    assert rows["p2g"]["bytes_per_particle"] == 108
    assert rows["g2p"]["bytes_per_particle"] == 252
    assert "bytes_per_particle" not in rows["grid_update"]  # a grid kernel: no particle streams
    # The limit is the copy bandwidth over what a steady sub-step streams (g2p's bytes); its share
    # is the measured rate over it (no assertion on the times themselves: wall clock).
    limit = report["copy_GB_per_s"] * 1e9 / 252
    assert abs(report["memory_limit_particle_substeps_per_s"] - limit) < 1e-6 * limit
    rate = report["substep_particle_substeps_per_s"]
    assert abs(report["substep_share_of_limit"] - rate / limit) < 1e-9 * rate / limit
    assert abs(rate - report["particles"] * 1e3 / rows["substep"]["ms"]) < 1e-6 * rate
