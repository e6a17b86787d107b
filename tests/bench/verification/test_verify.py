"""Fast versions of the solver verification cases (the finer ones run under -m slow / the bench)."""

from __future__ import annotations

import pytest

from physgm.bench.verification import analytic as V
from physgm.bench.verification import granular as VG


def _check(result):
    rows = result if isinstance(result, list) else [result]
    for row in rows:
        assert row["passed"], row


def test_free_fall_matches_symplectic_euler():
    _check(V.free_fall(fast=True))


def test_resting_block_does_not_sink_drift_or_gain_energy():
    _check(V.resting_block(fast=True))


def test_axial_bar_period():
    _check(V.bar_vibration(fast=True))


def test_cantilever_tip_deflection():
    _check(V.cantilever(fast=True))


def test_spinning_cube_keeps_angular_momentum():
    _check(V.spinning_cube(fast=True))


def test_colliding_spheres_keep_energy_and_separate():
    _check(V.colliding_spheres(fast=True))


def test_elastic_ball_restitution():
    _check(V.ball_restitution(fast=True, E=1e5))


def test_sand_pile_slope_is_the_friction_angle():
    _check(V.sand_pile(fast=True))


@pytest.mark.parametrize("aspect", VG.ASPECTS)
def test_column_collapse_runout_inside_the_experimental_band(aspect):
    """8-20 cells across L0 here (FAST_CELLS); 20 in the bench (python -m physgm.bench sim-verify)
    and under -m slow."""
    _check(VG.column_collapse(aspect, cells=VG.FAST_CELLS[aspect]))


def test_runout_band_and_deposit_front():
    import numpy as np

    assert VG.runout_band(1.0) == pytest.approx((0.8 * 1.2, 1.2 * 1.8))
    assert VG.runout_band(4.0) == pytest.approx((0.8 * 1.9 * 4 ** (2 / 3), 1.2 * 2.3 * 4 ** (2 / 3)))
    # A deposit of particles 1 cm apart out to x = 0.295 m, and one grain torn off at 0.5 m.
    x = np.array([[0.005 + 0.01 * i, 0.0, 0.005] for i in range(30)] + [[0.5, 0.0, 0.005]])
    front, top = VG.deposit_front(x, 0.01)
    assert front == pytest.approx(0.30) and top == pytest.approx(0.01)


def test_pile_slope_measures_a_known_cone():
    import numpy as np

    rng = np.random.default_rng(0)
    r = 0.2 * np.sqrt(rng.uniform(size=200_000))
    phi = rng.uniform(0, 2 * np.pi, r.size)
    z = rng.uniform(0, 1, r.size) * (0.2 - r) * np.tan(np.radians(30.0))  # 30 degree cone
    x = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    assert V.pile_slope(x, 0.01) == pytest.approx(30.0, abs=1.0)


@pytest.mark.slow
@pytest.mark.parametrize("case", range(len(V.all_cases(fast=False))))
def test_fine_verification(case):
    _check(V.all_cases(fast=False)[case]())
