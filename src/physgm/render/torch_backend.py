"""Plain-torch tiled rasteriser: the readable, autograd-differentiable reference.

Same math as the Warp backend, term for term: EWA projection (`projection.py`), binning to the
alpha >= 1/255 box, per-tile depth sort (stable, so ties keep Gaussian order), alpha =
min(0.99, o exp(-q / 2)), pairs with alpha < 1/255 skipped, and compositing front to back that
stops before the Gaussian that would bring transmittance below 1e-4. Slow (Python loop over
tiles) and memory hungry for large scenes; use it for tests and debugging.
"""

from __future__ import annotations

import torch
from torch import Tensor

from physgm.render.batch import SplatBatch
from physgm.render.projection import extents_from_cov, project_gaussians, radii_px, tile_rects
from physgm.render.settings import ALPHA_MAX, ALPHA_MIN, T_MIN, RasterSettings


def composite(
    alphas: Tensor,  # [P, G] per pixel and depth-sorted Gaussian, already clamped/zeroed
    colors: Tensor,  # [G, 3]
) -> tuple[Tensor, Tensor]:
    """Front-to-back alpha compositing with the early-stop rule.

    Returns:
        rgb [P, 3] (no background) and alpha [P] = 1 - final transmittance.
    """
    trans_after = torch.cumprod(1.0 - alphas, dim=1)  # [P, G] transmittance after each
    # Transmittance only decreases, so "stop before the first Gaussian with T_after < T_MIN"
    # is exactly this mask (skipped Gaussians have alpha 0 and weight 0 either way).
    keep = trans_after >= T_MIN
    trans_before = torch.cat([torch.ones_like(trans_after[:, :1]), trans_after[:, :-1]], dim=1)
    weights = alphas * trans_before * keep  # [P, G]
    return weights @ colors, weights.sum(dim=1)


def rasterize_torch(batch: SplatBatch, settings: RasterSettings) -> tuple[Tensor, Tensor, dict]:
    """Renders B x C images; returns rgb [B, C, H, W, 3] (no background), alpha [B, C, H, W, 1]."""
    num_b, num_c, num_n = batch.num_b, batch.num_c, batch.num_n
    means = batch.means  # [B, N, 3]; also gives the outputs' device and dtype
    width, height, tile = settings.width, settings.height, settings.tile_size
    proj = project_gaussians(batch, settings)
    opac = batch.opacities[:, None].expand(num_b, num_c, num_n)  # [B, C, N]
    extents = extents_from_cov(proj.cov_diag, opac)
    rect, nonempty = tile_rects(proj.means2d, extents, proj.visible, settings)

    num_images = num_b * num_c
    means2d = proj.means2d.reshape(num_images, num_n, 2)
    conics = proj.conics.reshape(num_images, num_n, 3)
    depths = proj.depths.reshape(num_images, num_n)
    rect = rect.reshape(num_images, num_n, 4)
    nonempty = nonempty.reshape(num_images, num_n)
    opac = opac.reshape(num_images, num_n)
    cols = batch.colors[:, None].expand(num_b, num_c, num_n, 3).reshape(num_images, num_n, 3)

    pieces_rgb, pieces_alpha, pieces_index = [], [], []
    n_isect = torch.zeros(num_images, dtype=torch.int64, device=means.device)
    for img in range(num_images):
        x0, x1, y0, y1 = rect[img].unbind(-1)  # [N] each
        for ty in range(settings.tiles_y):
            for tx in range(settings.tiles_x):
                hit = nonempty[img] & (x0 <= tx) & (tx <= x1) & (y0 <= ty) & (ty <= y1)
                idx = torch.nonzero(hit).squeeze(1)
                if idx.numel() == 0:
                    continue
                n_isect[img] += idx.numel()
                idx = idx[torch.sort(depths[img, idx], stable=True).indices]
                u = torch.arange(tx * tile, min((tx + 1) * tile, width), device=means.device)
                v = torch.arange(ty * tile, min((ty + 1) * tile, height), device=means.device)
                vv, uu = torch.meshgrid(v, u, indexing="ij")
                pix = torch.stack([uu, vv], dim=-1).reshape(-1, 2).to(means.dtype) + 0.5  # [P, 2]
                d = pix[:, None, :] - means2d[img, idx][None]  # [P, G, 2]
                con = conics[img, idx]  # [G, 3]
                dx, dy = d[..., 0], d[..., 1]
                q = con[:, 0] * dx * dx + 2.0 * con[:, 1] * dx * dy + con[:, 2] * dy * dy
                alpha = torch.clamp(opac[img, idx] * torch.exp(-0.5 * q), max=ALPHA_MAX)
                alpha = torch.where(alpha < ALPHA_MIN, torch.zeros_like(alpha), alpha)
                rgb, acc = composite(alpha, cols[img, idx])
                pieces_rgb.append(rgb)
                pieces_alpha.append(acc)
                pieces_index.append(((img * height + vv) * width + uu).reshape(-1))

    out_rgb = means.new_zeros(num_images * height * width, 3)
    out_alpha = means.new_zeros(num_images * height * width)
    if pieces_index:
        index = torch.cat(pieces_index)
        out_rgb = out_rgb.index_copy(0, index, torch.cat(pieces_rgb))
        out_alpha = out_alpha.index_copy(0, index, torch.cat(pieces_alpha))
    meta = {
        "means2d": proj.means2d.detach(),  # [B, C, N, 2] px
        "depths": proj.depths.detach(),  # [B, C, N] m
        "radii": radii_px(extents.detach(), nonempty.reshape(num_b, num_c, num_n)),
        "n_visible": nonempty.sum(-1).reshape(num_b, num_c),
        "n_intersections": n_isect.reshape(num_b, num_c),
    }
    shape = (num_b, num_c, height, width)
    return out_rgb.reshape(*shape, 3), out_alpha.reshape(*shape, 1), meta
