"""EWA projection of 3D Gaussians to screen space, in plain differentiable torch.

This is the reference for the Warp projection kernel (`warp_project_kernels.project_kernel`), which
mirrors it line by line. The 2D covariance of a Gaussian is J W R S S^T R^T W^T J^T + eps2d I,
with W the camera rotation and J the Jacobian of the perspective projection at the mean.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from physgm.render.batch import SplatBatch
from physgm.render.settings import (
    ALPHA_MIN,
    EXTENT_MARGIN_ABS,
    EXTENT_MARGIN_REL,
    FOV_CLAMP,
    RasterSettings,
)


@dataclass
class Projection:
    """Screen-space Gaussians for every (image, Gaussian) pair; culled pairs hold zeros.

    Attributes:
        means2d: Pixel position of the projected mean, [B, C, N, 2].
        conics: Upper triangle (a, b, c) of the inverse 2D covariance, [B, C, N, 3] (1/px^2).
        depths: Camera-space z of the mean, [B, C, N] (m).
        cov_diag: Diagonal of the dilated 2D covariance, [B, C, N, 2] (px^2).
        visible: In front of the camera, within the far plane, opacity >= 1/255, [B, C, N].
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    cov_diag: Tensor
    visible: Tensor


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices from quaternions (w, x, y, z), normalised here.

    Args:
        quats: [..., 4], any non-zero norm.

    Returns:
        [..., 3, 3] rotation matrices.
    """
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def project_gaussians(batch: SplatBatch, settings: RasterSettings) -> Projection:
    """Projects every Gaussian into every camera of its batch element (EWA splatting)."""
    means, quats, scales, viewmats, Ks = batch.means, batch.quats, batch.scales, batch.viewmats, batch.Ks
    rot_w = viewmats[..., :3, :3]  # [B, C, 3, 3]
    trans_w = viewmats[..., :3, 3]  # [B, C, 3]
    p_cam = torch.einsum("bcij,bnj->bcni", rot_w, means) + trans_w[:, :, None]  # [B, C, N, 3]
    x, y, z = p_cam.unbind(-1)
    visible = (z >= settings.near_plane) & (z <= settings.far_plane)
    visible = visible & (batch.opacities[:, None] >= ALPHA_MIN)
    z = torch.where(visible, z, torch.ones_like(z))  # culled pairs: finite values, no NaN grads

    fx, fy = Ks[..., 0, 0, None], Ks[..., 1, 1, None]  # [B, C, 1]
    cx, cy = Ks[..., 0, 2, None], Ks[..., 1, 2, None]
    width, height = settings.width, settings.height
    # Far off-screen Gaussians get the Jacobian of the image border (as 3DGS), else their
    # footprints blow up and smear across the image.
    lim_x = FOV_CLAMP * 0.5 * width / fx
    lim_y = FOV_CLAMP * 0.5 * height / fy
    tx = z * torch.minimum(torch.maximum(x / z, -cx / fx - lim_x), (width - cx) / fx + lim_x)
    ty = z * torch.minimum(torch.maximum(y / z, -cy / fy - lim_y), (height - cy) / fy + lim_y)
    zeros = torch.zeros_like(z)
    j0 = torch.stack([fx / z, zeros, -fx * tx / (z * z)], dim=-1)  # [B, C, N, 3]
    j1 = torch.stack([zeros, fy / z, -fy * ty / (z * z)], dim=-1)

    rot = torch.einsum("bcij,bnjk->bcnik", rot_w, quat_to_rotmat(quats))  # [B, C, N, 3, 3]
    s = scales[:, None]  # [B, 1, N, 3]
    a0 = torch.einsum("bcni,bcnik->bcnk", j0, rot) * s  # rows of A = J W R S, [B, C, N, 3]
    a1 = torch.einsum("bcni,bcnik->bcnk", j1, rot) * s
    eps = settings.eps2d
    cov_a0 = (a0 * a0).sum(-1)
    cov_b = (a0 * a1).sum(-1)
    cov_c0 = (a1 * a1).sum(-1)
    # det(A A^T + eps I) via Cauchy-Binet: a sum of squared 2x2 minors, which stays accurate for
    # needle-like Gaussians where a*c - b^2 cancels catastrophically in float32.
    m01 = a0[..., 0] * a1[..., 1] - a0[..., 1] * a1[..., 0]
    m02 = a0[..., 0] * a1[..., 2] - a0[..., 2] * a1[..., 0]
    m12 = a0[..., 1] * a1[..., 2] - a0[..., 2] * a1[..., 1]
    det = m01 * m01 + m02 * m02 + m12 * m12 + eps * (cov_a0 + cov_c0) + eps * eps
    visible = visible & (det > 0)
    det = torch.where(visible, det, torch.ones_like(det))
    cov_a, cov_c = cov_a0 + eps, cov_c0 + eps

    mask = visible[..., None]
    conics = torch.stack([cov_c / det, -cov_b / det, cov_a / det], dim=-1) * mask
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1) * mask
    cov_diag = torch.stack([cov_a, cov_c], dim=-1) * mask
    depths = z * visible
    return Projection(means2d, conics, depths, cov_diag, visible)


def extents_from_cov(
    cov_diag: Tensor,  # [..., 2] px^2
    opacities: Tensor,  # [...]
) -> Tensor:
    """Half-width and half-height (px) of the ellipse where opacity * G(d) >= 1/255.

    The ellipse d^T Sigma^-1 d <= 2 ln(255 o) is exactly the set of pixels that pass the alpha
    test, and its bounding box has half-sizes sqrt(k2 Sigma_xx), sqrt(k2 Sigma_yy). For o = 1
    this is 3.33 sigma, for o = 0.5 about 3 sigma. Binning to this box never drops a visible
    contribution, so every backend's output is independent of the tile size.

    Returns:
        [..., 2] extents in px (0 where opacity < 1/255).
    """
    k2 = 2.0 * torch.log(torch.clamp(opacities / ALPHA_MIN, min=1.0))
    ext = torch.sqrt(k2[..., None] * cov_diag)
    return ext * (1.0 + EXTENT_MARGIN_REL) + EXTENT_MARGIN_ABS * (k2[..., None] > 0)


def tile_rects(
    means2d: Tensor,  # [..., 2] px
    extents: Tensor,  # [..., 2] px
    visible: Tensor,  # [...] bool
    settings: RasterSettings,
) -> tuple[Tensor, Tensor]:
    """Inclusive tile ranges covered by each Gaussian's box, mirrored by the Warp `tile_rect`.

    A pixel (u, v) has its centre at (u + 0.5, v + 0.5), so the covered pixel columns are
    ceil(mx - rx - 0.5) .. floor(mx + rx - 0.5), clipped to the image.

    Returns:
        rect [..., 4] int64 (x0, x1, y0, y1) tile indices, and nonempty [...] bool.
    """
    lo = torch.ceil(means2d - extents - 0.5)
    hi = torch.floor(means2d + extents - 0.5)
    size = means2d.new_tensor([settings.width, settings.height])
    nonempty = visible & ((lo <= hi) & (hi >= 0) & (lo <= size - 1)).all(-1)
    lo = torch.minimum(torch.maximum(lo, torch.zeros_like(lo)), size - 1)
    hi = torch.minimum(torch.maximum(hi, torch.zeros_like(hi)), size - 1)
    lo_t = torch.div(lo, settings.tile_size, rounding_mode="floor").long()
    hi_t = torch.div(hi, settings.tile_size, rounding_mode="floor").long()
    rect = torch.stack([lo_t[..., 0], hi_t[..., 0], lo_t[..., 1], hi_t[..., 1]], dim=-1)
    return rect, nonempty


def radii_px(extents: Tensor, nonempty: Tensor) -> Tensor:
    """Integer screen radii per axis like gsplat's meta['radii'], [..., 2] int32 (0 = culled)."""
    return (torch.ceil(extents) * nonempty[..., None]).to(torch.int32)
