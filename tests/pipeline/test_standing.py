"""A photographed object stands on its base: what ``stand_on_base`` cuts flat, and what it leaves."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from physgm.gaussians import Gaussians
from physgm.pipeline.standing import TIP_DEG, describe, stand_on_base
from physgm.placement import place
from physgm.sim.planner.config import PlannerConfig


def _placed(points: np.ndarray):
    """Small opaque Gaussians at points [N, 3] (m), set with their lowest point on the ground z = 0."""
    n = len(points)
    g = Gaussians(
        means=torch.from_numpy(points).float(),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        scales=torch.full((n, 3), 2e-3),
        opacities=torch.ones(n),
        colors=torch.full((n, 3), 0.5),
    )
    return place(g, 1.0, (0.0, 0.0, float(points[:, 2].min())), (0.0, 0.0, 0.0))


def _can(sag: float, apex: float = 0.02, radius: float = 0.05, height: float = 0.2) -> np.ndarray:
    """The surface of a closed cylinder whose underside is a paraboloid dome, its lowest point
    ``apex`` (m) off the axis and its rim ``sag`` (m) above that point on the axis' other side."""
    rng = np.random.default_rng(0)

    def underside(x, y):
        return sag * ((x - apex) ** 2 + y**2) / (radius + apex) ** 2

    th = 2 * np.pi * rng.random(6000)
    x, y = radius * np.cos(th), radius * np.sin(th)
    low = underside(x, y)
    side = np.stack([x, y, low + (height - low) * rng.random(6000)], 1)
    r = radius * np.sqrt(rng.random((2, 2000)))  # top and bottom discs, uniform in area
    a = 2 * np.pi * rng.random((2, 2000))
    top = np.stack([r[0] * np.cos(a[0]), r[0] * np.sin(a[0]), np.full(2000, height)], 1)
    bx, by = r[1] * np.cos(a[1]), r[1] * np.sin(a[1])
    return np.concatenate([side, top, np.stack([bx, by, underside(bx, by)], 1)])


def _stand(points: np.ndarray):
    return stand_on_base(_placed(points), 0.05, 0.0, 0.3, PlannerConfig())


def test_a_can_with_a_domed_underside_is_cut_flat_and_stands():
    # A 10 cm wide, 20 cm tall can whose underside the model rounded into a dome, 15 mm deep, its
    # lowest point 2 cm off the axis: set down, it rolls towards that side.
    placed, base = _stand(_can(sag=0.015))
    assert base.turn_deg > TIP_DEG
    # The least cut that makes a base: 3 % (6 mm), where the base spans 0.63 of the widest section
    # and the can tilts 14 degrees before it tips; at 2 %, 0.47 of it but only 9 degrees.
    assert base.cut == pytest.approx(0.03) and base.cut_m == pytest.approx(0.006, rel=1e-3)
    assert base.turn_after_deg < 1.0
    z = placed.gaussians.means[:, 2].double()
    assert float(z.min()) == pytest.approx(0.0, abs=1e-6)  # the cut rests on the ground
    on_cut = int((z < 1e-6).sum())
    assert on_cut >= base.moved > 0  # the Gaussians below the cut were raised onto it
    # Everything above the cut just moved down by the cut's depth.
    before = _placed(_can(sag=0.015)).gaussians.means.double()
    above = before[:, 2] > base.cut_m + 1e-6
    torch.testing.assert_close(placed.gaussians.means.double()[above, 2], before[above, 2] - base.cut_m)
    assert placed.object_to_world[2, 3] == pytest.approx(
        _placed(_can(0.015)).object_to_world[2, 3] - base.cut_m
    )
    # The user is told what was cut, and the setting that keeps the shape.
    note = describe(base.as_dict())
    assert "lowest 6.0 mm (3 % of its height) were cut flat" in note and "object.stand=false" in note


def test_a_flat_bottomed_can_is_left_as_it_is():
    placed, base = _stand(_can(sag=0.0))
    assert base.turn_deg < 0.1 and base.cut == 0.0 and base.moved == 0
    assert describe(base.as_dict()) is None and describe(None) is None
    torch.testing.assert_close(placed.gaussians.means, _placed(_can(sag=0.0)).gaussians.means)


def test_round_bodies_and_bodies_on_an_edge_still_roll_or_fall():
    rng = np.random.default_rng(1)
    # An egg lying on its side at 20 degrees rolls: its lowest 8 % span 0.28 of its widest section,
    # too little for a base.
    d = rng.normal(size=(6000, 3))
    egg = d / np.linalg.norm(d, axis=1, keepdims=True) * [0.1, 0.06, 0.06]
    egg = egg @ Rotation.from_euler("y", 20, degrees=True).as_matrix().T
    _, base = _stand(egg)
    assert base.turn_deg > TIP_DEG and base.cut == 0.0
    # A 10 cm cube resting on an edge, tilted 15 degrees, falls onto its face: cut 7-8 % deep, its
    # edge spans 0.32-0.37 of its section, but the centre of mass is over the base's edge (-4 to 1
    # degrees of tilt before it tips), no base to stand a landing on.
    u = rng.random((6000, 3)) * 0.1
    u[np.arange(6000), rng.integers(0, 3, 6000)] = 0.1 * rng.integers(0, 2, 6000)  # on the faces
    cube = u @ Rotation.from_euler("y", 15, degrees=True).as_matrix().T
    _, base = _stand(cube)
    assert base.turn_deg > TIP_DEG and base.cut == 0.0
