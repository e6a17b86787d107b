"""Stage-1 losses: photometric (MSE, LPIPS), alpha against the mask, material CE, physics NLL,
and two optional terms on the Gaussians: an anisotropy penalty, and their centres' distance to
the ground-truth surface of synthetic assets.

Losses live here and in the LightningModules, never inside ``nn.Module.forward``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from physgm.model.posterior import PhysicsPosterior, PhysicsSample
from physgm.setting_types import check_types


@dataclass
class PretrainLossConfig:
    mse: float = 1.0  # weight of the RGB mean squared error
    lpips: float = 0.0  # weight of LPIPS (paper 0.5); its network: lpips_net (physgm.metrics.lpips)
    alpha: float = 1.0  # weight of the MSE between rendered alpha and the object mask
    ce: float = 0.1  # weight of the material cross-entropy against the annotation
    nll: float = 0.1  # weight of the Gaussian NLL of the annotated (log10 E, nu)
    aniso: float = 0.0  # weight of the anisotropy penalty (not in the paper; see ``anisotropy_penalty``)
    aniso_ratio: float = 4.0  # largest max/min scale ratio of a Gaussian that costs nothing
    # weight of the mean distance from the Gaussians' centres to the ground-truth surface (not in
    # the paper; see ``surface_distance``); needs data.surface_points > 0
    surface: float = 0.0
    surface_max_gaussians: int = 4096  # centres drawn per asset for the surface term
    # weight of the global tokens' relative squared distance to a frozen copy of the starting
    # model's (``token_anchor``): keeps the physics while stage.trainable=geometry trains the backbone
    anchor: float = 0.0
    lpips_net: str = "alex"  # alex or vgg (the lpips package), mobilenet (physgm.metrics.perceptual)
    lpips_backbone_path: str | None = None  # local torchvision weights; default torchvision's cache

    def __post_init__(self) -> None:
        check_types(self, "loss setting")
        if self.aniso < 0:
            raise ValueError(f"loss.aniso is a weight and must be >= 0, got {self.aniso}")
        if self.aniso_ratio < 1.0:
            raise ValueError(f"loss.aniso_ratio must be >= 1 (a sphere has ratio 1), got {self.aniso_ratio}")
        if self.surface < 0:
            raise ValueError(f"loss.surface is a weight and must be >= 0, got {self.surface}")
        if self.anchor < 0:
            raise ValueError(f"loss.anchor is a weight and must be >= 0, got {self.anchor}")
        if self.surface_max_gaussians < 1:
            raise ValueError(f"loss.surface_max_gaussians must be >= 1, got {self.surface_max_gaussians}")


def physics_nll(posterior: PhysicsPosterior, log10_E: Tensor, nu: Tensor) -> Tensor:  # [B]
    """Negative log density of the labelled (log10 E, nu) under the predicted Gaussians (normalised units)."""
    labels = PhysicsSample(
        torch.zeros_like(log10_E, dtype=torch.long)[:, None], log10_E[:, None], nu[:, None]
    )
    _, log_E, log_nu = posterior.log_prob_terms(labels)
    return -(log_E + log_nu)[:, 0]


def token_anchor(
    tokens: Tensor,  # [B, G, D] the trained backbone's global tokens
    reference: Tensor,  # [B, G, D] the frozen starting backbone's, for the same views
) -> Tensor:
    """Mean over scenes and tokens of |t - t_ref|^2 / |t_ref|^2.

    The physics head reads nothing but the global tokens, so holding them where the starting model
    put them holds its material, E and nu while the backbone learns better Gaussians.
    """
    return ((tokens - reference).square().sum(-1) / reference.square().sum(-1).clamp_min(1e-12)).mean()


def anisotropy_penalty(
    scales: Tensor,  # [B, N, 3] linear standard deviations
    valid: Tensor,  # [B, N] bool, Gaussians that exist (inside the input mask)
    max_ratio: float,
) -> Tensor:
    """Mean over valid Gaussians of relu(log(max scale / min scale) - log(max_ratio)).

    After the anisotropy regulariser of PhysGaussian (Xie et al. 2024; there on the plain ratio):
    needle- and sliver-like Gaussians fit the input views but show as hair from other directions
    and once the simulation rotates or stretches them. The log keeps the gradient bounded for the
    ratios of ~200 an unregularised head reaches (``scale_max / scale_min``).
    """
    if max_ratio < 1.0:
        raise ValueError(f"loss.aniso_ratio must be >= 1 (a sphere has ratio 1), got {max_ratio}")
    log_ratio = torch.log(scales.amax(-1) / scales.amin(-1).clamp_min(1e-12))
    excess = F.relu(log_ratio - math.log(max_ratio))
    weights = valid.to(excess.dtype)
    return (excess * weights).sum() / weights.sum().clamp_min(1.0)


def surface_distance(
    means: Tensor,  # [B, N, 3] predicted Gaussian centres
    valid: Tensor,  # [B, N] bool
    points: Tensor,  # [B, S, 3] ground-truth surface points (the asset's Gaussian centres)
    known: Tensor,  # [B] bool: the asset has ground-truth points
    max_gaussians: int,
) -> Tensor:
    """Mean over assets with ground truth of the mean distance from each valid predicted centre
    (at most ``max_gaussians`` of them, drawn at random) to its nearest ground-truth point.

    Not in the paper. Trained on images alone, the views' per-pixel depths disagree and their
    faint, wide Gaussians average the disagreement into a shape inflated to the views' visual hull
    (docs/model.md); synthetic assets know their surface, and this pulls every centre onto it.
    One-sided: a view sees only part of the surface, so nothing asks to cover the rest.
    """
    if not known.any():
        raise ValueError(
            "loss.surface > 0 but no asset of the batch has ground-truth points: set "
            "data.surface_points > 0 and train on assets with gaussians.ply (synthetic sets)"
        )
    out = []
    for b in torch.nonzero(known).flatten().tolist():
        m = means[b][valid[b]]
        if len(m) == 0:
            continue
        if len(m) > max_gaussians:
            m = m[torch.randperm(len(m), device=m.device)[:max_gaussians]]
        # exact differences: the matrix-product form loses ~1e-4 on distances of this size
        dist = torch.cdist(m, points[b].to(m), compute_mode="donot_use_mm_for_euclid_dist")
        out.append(dist.amin(dim=1).mean())
    return torch.stack(out).mean() if out else means.sum() * 0.0


def pretrain_losses(
    cfg: PretrainLossConfig,
    rgb: Tensor,  # [B, T, H, W, 3] rendered target views
    alpha: Tensor,  # [B, T, H, W, 1]
    target_rgb: Tensor,  # [B, T, 3, H, W]
    target_mask: Tensor,  # [B, T, 1, H, W]
    posterior: PhysicsPosterior,
    material: Tensor,  # [B] annotated material index
    log10_E: Tensor,  # [B] annotated log10 E
    nu: Tensor,  # [B] annotated nu
    lpips_model: nn.Module | None = None,
    scales: Tensor | None = None,  # [B, N, 3] predicted Gaussian scales, for loss.aniso
    valid: Tensor | None = None,  # [B, N] bool
    means: Tensor | None = None,  # [B, N, 3] predicted Gaussian centres, for loss.surface
    surface_points: Tensor | None = None,  # [B, S, 3] ground-truth surface points
    surface_known: Tensor | None = None,  # [B] bool
    tokens: Tensor | None = None,  # [B, G, D] global tokens, for loss.anchor
    reference_tokens: Tensor | None = None,  # [B, G, D] the frozen starting model's
) -> dict[str, Tensor]:
    """Weighted loss terms and their sum under ``"loss"``."""
    pred = rgb.permute(0, 1, 4, 2, 3)  # [B, T, 3, H, W]
    terms = {
        "mse": F.mse_loss(pred, target_rgb),
        "alpha": F.mse_loss(alpha.permute(0, 1, 4, 2, 3), target_mask),
        "ce": F.cross_entropy(posterior.material_logits, material),
        "nll": physics_nll(posterior, log10_E, nu).mean(),
    }
    if cfg.lpips > 0:
        if lpips_model is None:
            raise ValueError("loss.lpips > 0 but no LPIPS model was loaded")
        from physgm.metrics.lpips import lpips_distance

        terms["lpips"] = lpips_distance(lpips_model, pred, target_rgb)
    if cfg.aniso > 0:
        if scales is None or valid is None:
            raise ValueError("loss.aniso > 0 needs the predicted scales and valid flags")
        terms["aniso"] = anisotropy_penalty(scales, valid, cfg.aniso_ratio)
    if cfg.surface > 0:
        if means is None or valid is None or surface_points is None or surface_known is None:
            raise ValueError(
                "loss.surface > 0 needs the predicted centres and the batch's ground-truth surface "
                "points: set data.surface_points > 0"
            )
        terms["surface"] = surface_distance(
            means, valid, surface_points, surface_known, cfg.surface_max_gaussians
        )
    if cfg.anchor > 0:
        if tokens is None or reference_tokens is None:
            raise ValueError(
                "loss.anchor > 0 needs the global tokens of a frozen starting model: train with "
                "stage.trainable=geometry and stage.init_ckpt"
            )
        terms["anchor"] = token_anchor(tokens, reference_tokens)
    terms["loss"] = sum(getattr(cfg, name) * value for name, value in terms.items())
    return terms
