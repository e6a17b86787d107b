"""Backend that delegates to gsplat's CUDA rasteriser (optional dependency, CUDA only)."""

from __future__ import annotations

import torch
from torch import Tensor

from physgm.render.batch import SplatBatch
from physgm.render.settings import RasterSettings

_HOW_TO_SWITCH = (
    "Use backend='warp' (CPU and CUDA) or backend='torch' (slow reference) instead, "
    "e.g. `renderer=warp` on the Hydra command line."
)


def rasterize_gsplat(batch: SplatBatch, settings: RasterSettings) -> tuple[Tensor, Tensor, dict]:
    """Renders with `gsplat.rasterization` (classic mode, no background: the caller adds it)."""
    if batch.means.device.type != "cuda":
        raise ValueError(
            f"the gsplat backend needs CUDA tensors (gsplat's kernels are CUDA-only), got "
            f"device {batch.means.device}. {_HOW_TO_SWITCH}"
        )
    try:
        import gsplat
    except ImportError as err:
        raise ValueError(
            f"the gsplat backend needs the gsplat package (`pip install gsplat`). {_HOW_TO_SWITCH}"
        ) from err

    rgbs, alphas, metas = [], [], []
    # one call per batch element: works with every gsplat release (batch dims came in 1.5)
    for b in range(batch.num_b):
        rgb, alpha, meta = gsplat.rasterization(
            batch.means[b],
            batch.quats[b],
            batch.scales[b],
            batch.opacities[b],
            batch.colors[b],
            batch.viewmats[b],
            batch.Ks[b],
            settings.width,
            settings.height,
            near_plane=settings.near_plane,
            far_plane=settings.far_plane,
            eps2d=settings.eps2d,
            tile_size=settings.tile_size,
            packed=False,
            rasterize_mode="classic",
        )
        rgbs.append(rgb)
        alphas.append(alpha)
        metas.append(meta)
    radii = torch.stack([m["radii"] for m in metas])
    if radii.dim() == 3:  # older gsplat: one isotropic radius per Gaussian
        radii = radii[..., None].expand(*radii.shape, 2)
    visible = (radii > 0).all(-1)
    meta = {
        "means2d": torch.stack([m["means2d"] for m in metas]).detach(),
        "depths": torch.stack([m["depths"] for m in metas]).detach(),
        "radii": radii.to(torch.int32),
        "n_visible": visible.sum(-1),
        "gsplat": metas,
    }
    return torch.stack(rgbs), torch.stack(alphas), meta
