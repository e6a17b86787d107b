"""One scene through the model: posed views in, Gaussians and physics posterior out (on the CPU).

The one place a single scene is predicted, used by the pipeline (``simulate.py``), the DPO
rollouts and their evaluation, so all three see the same Gaussians for the same views.
"""

from __future__ import annotations

import torch
from torch import Tensor

from physgm.gaussians import Gaussians
from physgm.model.posterior import PhysicsPosterior


def predict_scene(
    model: torch.nn.Module,
    images: Tensor,  # [V, 3, H, W] in [0, 1]
    masks: Tensor,  # [V, 1, H, W]
    c2w: Tensor,  # [V, 4, 4] OpenCV camera-to-world
    Ks: Tensor,  # [V, 3, 3]
    classifier_images: Tensor | None = None,  # [V, 3, h, w] the views at a higher resolution, or None
) -> tuple[Gaussians, PhysicsPosterior]:
    """The model's valid Gaussians [N] (asset frame, float32, CPU) and physics posterior [1] (CPU).

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
    post = out.physics.detach()
    return g, post.cpu_float()
