"""Parameter counts and CPU forward time of a PhysGM (used by ``physgm.bench model`` and the sweep table)."""

from __future__ import annotations

import time

import torch

from physgm.cameras import orbit_cameras
from physgm.model.physgm import PhysGM


def count_parameters(model: PhysGM) -> dict[str, int]:
    """Parameters in total, trainable, and per part."""

    def n(params) -> int:
        return sum(p.numel() for p in params)

    return {
        "total": n(model.parameters()),
        "trainable": n(p for p in model.parameters() if p.requires_grad),
        "encoder": n(model.backbone.encoder.parameters()),
        "joint_backbone": n(model.backbone.parameters()) - n(model.backbone.encoder.parameters()),
        "gaussian_head": n(model.gaussian_head.parameters()),
        "physics_head": n(model.physics_head.parameters()),
    }


def forward_milliseconds(model: PhysGM, views: int, size: int, repeats: int) -> list[float]:
    """Wall-clock milliseconds of ``repeats`` forwards of one scene (after one warm-up run).

    Inputs are random ``size`` px views on an orbit with an all-object mask, so every pixel
    makes a Gaussian (the most expensive case). With ``repeats == 0`` the only run is timed.
    """
    cams = orbit_cameras([i * 360.0 / views for i in range(views)], [20.0] * views, 1.5, 40.0, size, size)
    device = next(model.parameters()).device
    images = torch.rand(1, views, 3, size, size, device=device)
    masks = torch.ones(1, views, 1, size, size, device=device)
    c2w, Ks = cams.c2w[None].to(device), cams.Ks[None].to(device)
    was_training = model.training
    model.eval()
    timings = []
    with torch.inference_mode():
        for i in range(repeats + 1):  # the first run warms up allocators and kernels
            start = time.perf_counter()
            model(images, masks, c2w, Ks)
            if i > 0 or repeats == 0:
                timings.append(1000.0 * (time.perf_counter() - start))
    model.train(was_training)
    return timings
