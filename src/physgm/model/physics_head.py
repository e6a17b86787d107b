"""Physics head: the 3 global tokens -> ``PhysicsPosterior`` (material, log10 E, nu).

One token per quantity, as in the paper: token 0 gives the material logits, token 1 the mean and
log-variance of normalised log10 E, token 2 those of normalised nu (normalisation in
``physgm.model.posterior``). This is the only module the DPO stage trains.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from physgm.model.config import PhysicsHeadConfig
from physgm.model.posterior import PhysicsPosterior


class PhysicsHead(nn.Module):
    """Decodes the global tokens into a physics posterior."""

    def __init__(self, cfg: PhysicsHeadConfig, dim: int, num_global_tokens: int) -> None:
        super().__init__()
        if num_global_tokens < 3:
            raise ValueError(
                f"the physics head reads 3 global tokens, backbone.num_global_tokens is {num_global_tokens}"
            )
        if not cfg.logvar_min < cfg.logvar_max:
            raise ValueError(
                f"physics_head needs logvar_min < logvar_max, got {cfg.logvar_min}, {cfg.logvar_max}"
            )
        self.cfg = cfg
        self.material = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, cfg.num_materials))
        self.young = _mean_logvar_mlp(dim, cfg.hidden)
        self.poisson = _mean_logvar_mlp(dim, cfg.hidden)
        nn.init.normal_(self.material[-1].weight, std=0.02)
        nn.init.zeros_(self.material[-1].bias)

    def forward(
        self,
        global_tokens: Tensor,  # [B, G >= 3, D]
    ) -> PhysicsPosterior:
        E_mean, E_raw = self.young(global_tokens[:, 1]).unbind(-1)
        nu_mean, nu_raw = self.poisson(global_tokens[:, 2]).unbind(-1)
        return PhysicsPosterior(
            material_logits=self.material(global_tokens[:, 0]),
            z_E_mean=E_mean,
            z_E_logvar=self._logvar(E_raw) + self.cfg.E_logvar_offset,
            z_nu_mean=nu_mean,
            z_nu_logvar=self._logvar(nu_raw) + self.cfg.nu_logvar_offset,
        )

    def _logvar(self, raw: Tensor) -> Tensor:
        # Smoothly bounded: a vanishing variance would let the NLL run to -inf on one sample.
        lo, hi = self.cfg.logvar_min, self.cfg.logvar_max
        return lo + (hi - lo) * torch.sigmoid(raw)


def _mean_logvar_mlp(dim: int, hidden: int) -> nn.Sequential:
    mlp = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, 2))
    # Start at the centre of the normalised range with a middling variance.
    nn.init.normal_(mlp[-1].weight, std=0.01)
    nn.init.zeros_(mlp[-1].bias)
    return mlp


def fuse_material_logits(
    head_logits: Tensor,  # [B, M]
    semantic_log_prior: Tensor | None,  # [B, M] log p_prior(material), or None
    weight: float,
) -> Tensor:  # [B, M]
    """Material logits of p_head * p_prior^weight (the head's own logits without a prior or at 0)."""
    if semantic_log_prior is None or weight == 0.0:
        return head_logits
    return head_logits.log_softmax(dim=-1) + weight * semantic_log_prior.to(head_logits.dtype)
