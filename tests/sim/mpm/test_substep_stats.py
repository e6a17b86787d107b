"""The G2P kernel's per-thread reductions, read by name: each column reduced the way it was accumulated."""

from __future__ import annotations

import math

import numpy as np

from physgm.sim.mpm import kernels as K
from physgm.sim.mpm.solver import SubstepStats


def _row(v2: float, j_min: float, j_max: float, bad: int, escaped: int, overrun: int) -> np.ndarray:
    row = np.zeros(K.STATS_ROW, np.float32)
    row[[K.STAT_VMAX, K.STAT_JMIN, K.STAT_JMAX]] = v2, j_min, j_max
    row[[K.STAT_BAD, K.STAT_ESCAPED, K.STAT_OVERRUN]] = bad, escaped, overrun
    return row


def test_threads_are_reduced_per_column_and_speed_is_the_root():
    s = SubstepStats.reduce(np.stack([_row(4.0, 0.9, 1.1, 0, 2, 0), _row(9.0, 0.95, 1.3, 0, 1, 3)]))
    assert s.max_speed == 3.0  # the kernel keeps |v|^2; the larger of the two threads
    assert math.isclose(s.j_min, 0.9, rel_tol=1e-6) and math.isclose(s.j_max, 1.3, rel_tol=1e-6)
    assert (s.bad, s.escaped, s.overrun) == (0, 3, 3) and s.finite


def test_a_bad_particle_or_a_nan_makes_the_state_not_finite():
    assert not SubstepStats.reduce(_row(1.0, 1.0, 1.0, 1, 0, 0)[None]).finite
    assert not SubstepStats.reduce(_row(1.0, float("nan"), 1.0, 0, 0, 0)[None]).finite
    # in either thread's row, for every column (Python's min and max would keep the other value)
    for col in range(3):
        good, bad = _row(1.0, 1.0, 1.0, 0, 0, 0), _row(1.0, 1.0, 1.0, 0, 0, 0)
        bad[col] = float("nan")
        assert not SubstepStats.reduce(np.stack([good, bad])).finite
        assert not SubstepStats.reduce(np.stack([bad, good])).finite
