"""Physics head: the 3 global tokens -> ``PhysicsPosterior`` (material, log10 E, nu).

One token per quantity, as in the paper: token 0 gives the material logits, token 1 the mean and
log-variance of normalised log10 E, token 2 those of normalised nu (normalisation in
``physgm.model.posterior``). With ``material_input="features"`` the material logits come instead
from the frozen CNN encoder's pyramid, pooled over space and views (``pooled_features``): on the
synthetic assets that reads the material better than the jointly trained token does, while the
tokens read E better (docs/model.md). With ``procedural_expert`` the head has both: the token
classifier for real objects (inside the semantic prior's product) and a pooled-features one for the
scenes the domain gate calls procedural (``fuse_material_logits``). This is the only module the DPO
stage trains.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from physgm.model.cnn_encoder import LEVEL_CHANNELS, ImageFeatures
from physgm.model.config import PhysicsHeadConfig
from physgm.model.posterior import PhysicsPosterior, material_E_ranges

MATERIAL_INPUTS = ("token", "features")
E_FRAMES = ("global", "material")
# Per-channel mean of all four levels and standard deviation of the two coarsest (the fine levels'
# spread is mostly the silhouette's edge).
POOLED_DIM = sum(LEVEL_CHANNELS.values()) + LEVEL_CHANNELS["s16"] + LEVEL_CHANNELS["s32"]


def pooled_features(
    features: ImageFeatures,  # [B * V, ...] or [B, V, ...] frozen-encoder outputs
    batch: int,  # B
) -> Tensor:  # [B, POOLED_DIM]
    """One vector per scene: the pyramid pooled over space, then averaged over the scene's views."""
    levels = [t.float().flatten(0, -4) for t in features.levels()]  # [B * V, C, h, w]
    parts = [t.mean((-2, -1)) for t in levels] + [t.std((-2, -1), correction=0) for t in levels[2:]]
    return torch.cat(parts, -1).reshape(batch, -1, POOLED_DIM).mean(1)


class PooledMaterialClassifier(nn.Module):
    """Material logits from ``pooled_features``: standardise, then a one-hidden-layer MLP.

    ``shift`` / ``scale`` are the training set's per-feature mean and standard deviation
    (buffers, set by ``physgm.train.refit_material``). ``dropout`` (input, hidden) is 0 outside
    that fit, so the DPO stage's log-probabilities stay deterministic.
    """

    def __init__(self, num_materials: int, hidden: int) -> None:
        super().__init__()
        self.register_buffer("shift", torch.zeros(POOLED_DIM))
        self.register_buffer("scale", torch.ones(POOLED_DIM))
        self.hidden = nn.Linear(POOLED_DIM, hidden)
        self.out = nn.Linear(hidden, num_materials)
        self.dropout = (0.0, 0.0)

    def forward(self, pooled: Tensor) -> Tensor:  # [B, POOLED_DIM] -> [B, M]
        x = nn.functional.dropout((pooled - self.shift) / self.scale, self.dropout[0], self.training)
        h = nn.functional.dropout(nn.functional.gelu(self.hidden(x)), self.dropout[1], self.training)
        return self.out(h)


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
        if not cfg.semantic_prior_temperature > 0:
            raise ValueError(
                f"physics_head.semantic_prior_temperature must be > 0, got {cfg.semantic_prior_temperature}"
            )
        if not cfg.material_temperature > 0:
            raise ValueError(f"physics_head.material_temperature must be > 0, got {cfg.material_temperature}")
        if cfg.material_input not in MATERIAL_INPUTS:
            raise ValueError(
                f"physics_head.material_input must be one of {MATERIAL_INPUTS}, got {cfg.material_input!r}"
            )
        if cfg.procedural_expert and cfg.material_input == "features":
            raise ValueError(
                "physics_head.procedural_expert adds a pooled-features classifier beside the token one; "
                "material_input='features' already reads the pooled features: use one or the other"
            )
        if cfg.E_frame not in E_FRAMES:
            raise ValueError(f"physics_head.E_frame must be one of {E_FRAMES}, got {cfg.E_frame!r}")
        self.cfg = cfg
        # [M, 2] log10 E range per material, for E_frame "material" (not saved: the material table's)
        self.register_buffer("E_ranges", material_E_ranges(), persistent=False)
        if cfg.E_frame == "material" and len(self.E_ranges) != cfg.num_materials:
            raise ValueError(
                f"physics_head.E_frame='material' reads the material table's {len(self.E_ranges)} E ranges, "
                f"but the head has num_materials={cfg.num_materials}"
            )
        if cfg.material_input == "features":
            self.material = PooledMaterialClassifier(cfg.num_materials, cfg.feature_hidden)
            last = self.material.out
        else:
            self.material = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, cfg.num_materials))
            last = self.material[-1]
        self.procedural = None
        if cfg.procedural_expert:
            self.procedural = PooledMaterialClassifier(cfg.num_materials, cfg.feature_hidden)
            nn.init.normal_(self.procedural.out.weight, std=0.02)
            nn.init.zeros_(self.procedural.out.bias)
        self.young = _mean_logvar_mlp(dim, cfg.hidden)
        self.poisson = _mean_logvar_mlp(dim, cfg.hidden)
        nn.init.normal_(last.weight, std=0.02)
        nn.init.zeros_(last.bias)

    def forward(
        self,
        global_tokens: Tensor,  # [B, G >= 3, D]
        pooled: Tensor | None = None,  # [B, POOLED_DIM] pooled_features, for material_input "features"
    ) -> PhysicsPosterior:
        """The posterior; its material logits are the main classifier's (token or features), never the
        procedural expert's (``procedural_logits``)."""
        if self.cfg.material_input == "features":
            material_logits = self.material(self._need_pooled(pooled))
        else:
            material_logits = self.material(global_tokens[:, 0])
        E_mean, E_raw = self.young(global_tokens[:, 1]).unbind(-1)
        nu_mean, nu_raw = self.poisson(global_tokens[:, 2]).unbind(-1)
        return PhysicsPosterior(
            material_logits=material_logits,
            z_E_mean=E_mean,
            z_E_logvar=self._logvar(E_raw) + self.cfg.E_logvar_offset,
            z_nu_mean=nu_mean,
            z_nu_logvar=self._logvar(nu_raw) + self.cfg.nu_logvar_offset,
            E_ranges=self.E_ranges if self.cfg.E_frame == "material" else None,
        )

    def procedural_logits(self, pooled: Tensor | None) -> Tensor | None:  # [B, POOLED_DIM] -> [B, M]
        """The procedural expert's material logits, or None for a head without one."""
        return None if self.procedural is None else self.procedural(self._need_pooled(pooled))

    def _need_pooled(self, pooled: Tensor | None) -> Tensor:
        if pooled is None:
            raise ValueError(
                "this physics head reads the material from the CNN encoder's pooled features; "
                "pass physics_head(global_tokens, pooled_features(features, B))"
            )
        return pooled

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
    temperature: float = 1.0,
    gate: Tensor | None = None,  # [B] the domain gate's P(real object), or None
    procedural_logits: Tensor | None = None,  # [B, M] the procedural expert's, or None (needs a gate)
) -> Tensor:  # [B, M]
    """Material logits of p^(1 / temperature), where p = p_head * p_prior^weight (normalised), or with a
    domain gate g the mixture g * that + (1 - g) * p_procedural: the prior's expert where the scene
    looks real, the procedural expert (the head itself when there is none) where it looks like the
    procedural training data. Without a prior or at weight 0 the real expert is p_head alone, and
    without a gate too the result is the head's own logits."""
    if procedural_logits is not None and gate is None:
        raise ValueError("a procedural expert's logits are mixed in by the domain gate's g; pass gate")
    fused = head_logits
    if semantic_log_prior is not None and weight != 0.0:
        log_prior = semantic_log_prior.to(head_logits.dtype)
        fused = (head_logits.log_softmax(dim=-1) + weight * log_prior).log_softmax(dim=-1)
    if gate is not None:
        other = head_logits if procedural_logits is None else procedural_logits
        g = gate.to(head_logits.dtype)[:, None]  # log(0) = -inf drops an expert exactly
        real, procedural = fused.log_softmax(dim=-1), other.log_softmax(dim=-1)
        fused = torch.logaddexp(g.log() + real, (1 - g).log() + procedural)
    return fused if temperature == 1.0 else fused / temperature
