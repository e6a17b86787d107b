"""Placing an object: the anchor lands on the target, sizes scale, and the 4x4 says what was done."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from physgm.gaussians import Gaussians
from physgm.placement import place


def test_anchor_lands_on_target_and_the_transform_reproduces_the_means():
    gen = torch.Generator().manual_seed(0)
    n = 50
    g = Gaussians(
        torch.rand(n, 3, generator=gen) - 0.5,
        torch.nn.functional.normalize(torch.rand(n, 4, generator=gen), dim=-1),
        torch.rand(n, 3, generator=gen) * 0.05 + 0.01,
        torch.rand(n, generator=gen),
        torch.rand(n, 3, generator=gen),
    )
    lowest = float(g.means[:, 2].min())
    p = place(g, 0.3, (0.1, -0.2, lowest), (0.0, 0.0, 0.25))
    assert p.scale == 0.3 and p.gaussians.means.dtype == torch.float32
    assert float(p.gaussians.means[:, 2].min()) == pytest.approx(0.25, abs=1e-6)
    torch.testing.assert_close(p.gaussians.scales, g.scales * 0.3)
    assert torch.equal(p.gaussians.quats, g.quats) and torch.equal(p.gaussians.colors, g.colors)
    homogeneous = np.concatenate([g.means.double().numpy(), np.ones((n, 1))], 1)
    np.testing.assert_allclose(
        (homogeneous @ p.object_to_world.T)[:, :3], p.gaussians.means.numpy(), atol=1e-6
    )
    anchor_world = p.object_to_world @ np.array([0.1, -0.2, lowest, 1.0])
    np.testing.assert_allclose(anchor_world[:3], [0.0, 0.0, 0.25], atol=1e-12)
