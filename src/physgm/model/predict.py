"""One scene through the model: posed views in, Gaussians and physics posterior out (on the CPU).

The one place a single scene is predicted, used by the pipeline (``simulate.py``), the DPO
rollouts and their evaluation, so all three see the same Gaussians for the same views.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from physgm.gaussians import Gaussians
from physgm.model.posterior import PhysicsPosterior


@dataclass
class ScenePrediction:
    """What the model predicts for one scene, on the CPU."""

    gaussians: Gaussians  # [N] the valid ones, asset frame, float32
    posterior: PhysicsPosterior  # [1]
    domain_real: float | None  # the domain gate's P(real object), None for a model without a gate


def predict_scene(
    model: torch.nn.Module,
    images: Tensor,  # [V, 3, H, W] in [0, 1]
    masks: Tensor,  # [V, 1, H, W]
    c2w: Tensor,  # [V, 4, 4] OpenCV camera-to-world
    Ks: Tensor,  # [V, 3, 3]
    classifier_images: Tensor | None = None,  # [V, 3, h, w] the views at a higher resolution, or None
) -> ScenePrediction:
    """The model's valid Gaussians, physics posterior and domain gate for one scene.

    Runs in eval mode without gradients on the model's own device; every submodule's train/eval
    flag is restored afterwards one by one, so a module frozen in eval (the DPO policy's backbone)
    stays in eval. ``classifier_images`` go to the frozen CNN encoder's ImageNet classifier
    (``PhysGM.encode_views``).
    """
    device = next(model.parameters()).device
    modes = {m: m.training for m in model.modules()}
    model.eval()
    try:
        with torch.no_grad():
            sharp = None if classifier_images is None else classifier_images.to(device)
            features = model.encode_views(images.to(device), sharp)
            out = model(
                images[None].to(device),
                masks[None].to(device),
                c2w[None].to(device),
                Ks[None].to(device),
                features,
            )
    finally:
        for m, mode in modes.items():
            m.training = mode
    g = out.gaussians.to_gaussians(0)
    g = Gaussians(*(t.detach().float().cpu() for t in (g.means, g.quats, g.scales, g.opacities, g.colors)))
    gate = None if out.domain_real is None else float(out.domain_real[0])
    return ScenePrediction(g, out.physics.detach().cpu_float(), gate)
