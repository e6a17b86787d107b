"""Putting an object into the simulation world: a uniform scale and a shift, and the 4x4 recording them.

Objects come in an object frame (the model's normalised frame or an asset's, +z up) and are
simulated in metres above the ground plane. The pipeline (``physgm.pipeline.staging``: a chosen
physical size, the object's middle over the origin) and the reference videos and their DPO
rollouts (``physgm.data.video``: the asset's fixed scale, dropped from a height) choose the scale
and the anchor differently; the placing itself is this one function.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from physgm.gaussians import Gaussians


@dataclass
class Placement:
    """The object in the world, before the scene moves it."""

    gaussians: Gaussians  # [N] world frame, m, +z up
    object_to_world: np.ndarray  # [4, 4] object frame -> world (uniform scale, then shift)
    scale: float  # m per object-frame unit


def place(
    g: Gaussians,  # [N] object frame
    scale: float,  # m per object-frame unit
    anchor: Sequence[float],  # [3] object-frame point ...
    target: Sequence[float],  # [3] ... that lands here in the world, m
) -> Placement:
    """``g`` scaled by ``scale`` about ``anchor``, which moves to ``target``; rotations and colours are kept.

    The arithmetic is float64 (object-to-world shifts are metres against sub-millimetre Gaussians),
    the result in ``g``'s dtype.
    """
    anchor_t = torch.as_tensor(anchor, dtype=torch.float64)
    shift = torch.as_tensor(target, dtype=torch.float64) - anchor_t * scale
    T = np.eye(4)
    T[:3, :3] *= scale
    T[:3, 3] = shift.numpy()
    placed = Gaussians(
        means=(g.means.double() * scale + shift.to(g.means.device)).to(g.means.dtype),
        quats=g.quats,
        scales=g.scales * scale,
        opacities=g.opacities,
        colors=g.colors,
    )
    return Placement(placed, T, float(scale))
