"""Domain gate: how much a scene looks like a real object rather than a procedural training asset.

The semantic prior (``physgm.model.semantic_prior``) names the material of real objects from the
ImageNet class they resemble, and on procedural shapes it is noise; the physics head is the other
way round (docs/model.md: w = 16 gives real test objects 0.64 and synthetic ones 0.07). Neither
one's confidence tells the two domains apart, but the frozen encoder's pooled pyramid does: a
logistic regression on it separates held-out real objects from held-out synthetic assets.

The gate is that regression, applied to every view and averaged in logit space over a scene's
views. Its probability ``g`` weighs two experts: the material distribution is the mixture
``g * norm(p_head * p_prior^w) + (1 - g) * p_procedural`` (``fuse_material_logits``), the prior's
fusion where the scene looks real and the procedural expert (the head itself when the model has
none) where it looks procedural. It is fitted after stage 1 by ``python -m physgm.train.fit_gate``
on the synthetic training assets against real objects of their own set (``python -m
physgm.data.real_objects --set gate``), never on the real evaluation set. Its numbers are
buffers: no stage trains them, and DPO's log-probabilities see them as constants.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from physgm.model.cnn_encoder import ImageFeatures
from physgm.model.physics_head import POOLED_DIM, pooled_features


class DomainGate(nn.Module):
    """P(real object) of each scene from its views' pooled encoder features."""

    def __init__(self) -> None:
        super().__init__()
        # Standardisation of the pooled features (the fit's training views) and the regression.
        self.register_buffer("shift", torch.zeros(POOLED_DIM))
        self.register_buffer("scale", torch.ones(POOLED_DIM))
        self.register_buffer("weight", torch.zeros(POOLED_DIM))
        self.register_buffer("bias", torch.zeros(()))

    def view_logits(self, pooled: Tensor) -> Tensor:  # [..., POOLED_DIM] -> [...]
        """log-odds of "real" for single views' pooled features."""
        return ((pooled.float() - self.shift) / self.scale) @ self.weight + self.bias

    def forward(
        self,
        features: ImageFeatures,  # [B, V, ...] or [B * V, ...] frozen-encoder outputs
        batch: int,  # B
    ) -> Tensor:  # [B] probability in (0, 1)
        views = features.s4.flatten(0, -4).shape[0]  # B * V
        per_view = pooled_features(features, batch=views)  # [B * V, POOLED_DIM]
        return self.scene_probability(per_view.reshape(batch, -1, POOLED_DIM))

    def scene_probability(self, per_view: Tensor) -> Tensor:  # [B, V, POOLED_DIM] -> [B]
        """The gate of scenes whose views are already pooled one by one."""
        return torch.sigmoid(self.view_logits(per_view).mean(dim=1))

    def set_fit(self, shift: Tensor, scale: Tensor, weight: Tensor, bias: float) -> None:
        """Store a fitted regression (``physgm.train.fit_gate``)."""
        for name, value in (("shift", shift), ("scale", scale), ("weight", weight)):
            if value.shape != (POOLED_DIM,):
                raise ValueError(f"gate {name} must have shape ({POOLED_DIM},), got {tuple(value.shape)}")
            getattr(self, name).copy_(value)
        self.bias.fill_(float(bias))
