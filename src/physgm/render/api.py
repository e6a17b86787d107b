"""`rasterize`: the one entry point of the renderer, shaped like gsplat's `rasterization`."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Protocol

import torch
from torch import Tensor

from physgm.render.batch import SplatBatch
from physgm.render.gsplat_backend import rasterize_gsplat
from physgm.render.settings import RasterSettings, single_threaded_torch
from physgm.render.torch_backend import rasterize_torch
from physgm.render.validate import validate_inputs
from physgm.render.warp_backend import rasterize_warp

# name -> backend(batch, settings) -> (rgb [B,C,H,W,3] without background, alpha [B,C,H,W,1], meta)
BACKENDS: dict[str, Callable[[SplatBatch, RasterSettings], tuple[Tensor, Tensor, dict]]] = {
    "warp": rasterize_warp,
    "torch": rasterize_torch,
    "gsplat": rasterize_gsplat,
}


def rasterize(
    means: Tensor,  # [..., N, 3] world (m)
    quats: Tensor,  # [..., N, 4] (w, x, y, z), normalised inside
    scales: Tensor,  # [..., N, 3] linear std (m)
    opacities: Tensor,  # [..., N] in [0, 1]
    colors: Tensor,  # [..., N, 3] RGB
    viewmats: Tensor,  # [..., C, 4, 4] world-to-camera, OpenCV
    Ks: Tensor,  # [..., C, 3, 3] pixel intrinsics
    width: int,
    height: int,
    background: Tensor | None = None,  # [3] or [..., C, 3]; None is black
    backend: str = "warp",
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    tile_size: int = 16,
    num_threads: int = 2,
) -> tuple[Tensor, Tensor, dict]:
    """Renders Gaussians into C cameras per batch element with EWA splatting.

    Each batch element (leading dims "...") has its own Gaussians and cameras, and all
    batch x camera images are rendered in one call. Differentiable w.r.t. means, quats,
    scales, opacities, colors and background (not viewmats / Ks: the warp backend returns no
    camera gradients).

    Args:
        means, quats, scales, opacities, colors: Gaussians, see shape comments.
        viewmats, Ks: Cameras (OpenCV world-to-camera, pixel intrinsics; skew ignored).
        width, height: Image size (px).
        background: Colour behind the Gaussians, blended with 1 - alpha.
        backend: "warp" (CPU + CUDA), "torch" (slow reference) or "gsplat" (CUDA).
        near_plane, far_plane: Depth range (m); Gaussians outside are culled.
        eps2d: Screen-space dilation (px^2) added to each 2D covariance.
        tile_size: Screen tile side (px) for binning; does not change the image beyond float
            rounding. The warp backend's CPU layout handles at most 16 (one SIMD row per tile
            row); with larger tiles it runs the slower pixel layout.
        num_threads: CPU threads for the warp raster kernels.

    Returns:
        rgb [..., C, H, W, 3], alpha [..., C, H, W, 1], and meta with means2d [..., C, N, 2],
        depths [..., C, N], radii [..., C, N, 2] (int px, 0 = culled), n_visible [..., C]
        (Gaussians whose footprint touches the image) and, for warp/torch, n_intersections
        [..., C] (Gaussian-tile pairs).

    Raises:
        ValueError: bad shapes, dtypes, devices, values or backend name.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {sorted(BACKENDS)}, got {backend!r}")
    if isinstance(tile_size, bool) or not isinstance(tile_size, int) or tile_size <= 0:
        raise ValueError(f"tile_size must be a positive int (px), got {tile_size!r}")
    if isinstance(num_threads, bool) or not isinstance(num_threads, int) or num_threads <= 0:
        raise ValueError(f"num_threads must be a positive int, got {num_threads!r}")
    # the checks and the warp backend's glue are many small ops, see single_threaded_torch
    with single_threaded_torch() if backend == "warp" else contextlib.nullcontext():
        gauss, cams = (means, quats, scales, opacities, colors), (viewmats, Ks)
        lead, num_n, num_c = validate_inputs(
            gauss, cams, width, height, background, near_plane, far_plane, eps2d
        )
        settings = RasterSettings(
            width, height, float(near_plane), float(far_plane), float(eps2d), tile_size, num_threads
        )
        num_b = math.prod(lead)
        batch = SplatBatch(
            *(x.reshape(num_b, num_n, *x.shape[len(lead) + 1 :]) for x in gauss),
            *(x.reshape(num_b, num_c, *x.shape[len(lead) + 1 :]) for x in cams),
        )

        if num_n == 0 or num_c == 0:
            rgb = means.new_zeros(num_b, num_c, height, width, 3)
            alpha = means.new_zeros(num_b, num_c, height, width, 1)
            meta = _empty_meta(means, num_b, num_c, num_n)
        else:
            rgb, alpha, meta = BACKENDS[backend](batch, settings)
        rgb, alpha = _keep_graph(rgb, batch.gaussians()), _keep_graph(alpha, batch.gaussians())

        if background is not None:
            bg = background if background.dim() == 1 else background.reshape(num_b, num_c, 1, 1, 3)
            rgb = rgb + (1.0 - alpha) * bg
        out_shape = (*lead, num_c, height, width)
        meta = {k: (v.reshape(*lead, *v.shape[1:]) if isinstance(v, Tensor) else v) for k, v in meta.items()}
        return rgb.reshape(*out_shape, 3), alpha.reshape(*out_shape, 1), meta


class SplatFields(Protocol):
    """What `rasterize_gaussians` reads: physgm.gaussians.Gaussians ([N]) or the model's
    GaussianPrediction ([B, N]) alike."""

    means: Tensor  # [..., N, 3]
    quats: Tensor  # [..., N, 4]
    scales: Tensor  # [..., N, 3]
    opacities: Tensor  # [..., N]
    colors: Tensor  # [..., N, 3]


def rasterize_gaussians(
    g: SplatFields,
    viewmats: Tensor,  # [..., C, 4, 4]
    Ks: Tensor,  # [..., C, 3, 3]
    width: int,
    height: int,
    **options,  # rasterize's background, backend, near_plane, far_plane, eps2d, tile_size, num_threads
) -> tuple[Tensor, Tensor, dict]:
    """`rasterize` of a Gaussians container."""
    return rasterize(
        g.means, g.quats, g.scales, g.opacities, g.colors, viewmats, Ks, width, height, **options
    )


def _keep_graph(out: Tensor, inputs: tuple[Tensor, ...]) -> Tensor:
    """Keeps an output attached to the inputs when nothing was drawn (N = 0, all culled).

    Then it does not depend on them and `loss.backward()` would fail with "does not require
    grad"; adding 0 * sum(x) gives the caller zero gradients of the right shapes instead.
    """
    if out.requires_grad or not torch.is_grad_enabled():
        return out
    needing = [x for x in inputs if x.requires_grad]
    if not needing:
        return out
    return out + sum(x.sum() for x in needing) * 0.0


def _empty_meta(means: Tensor, num_b: int, num_c: int, num_n: int) -> dict:
    zeros_i = torch.zeros(num_b, num_c, dtype=torch.int64, device=means.device)
    return {
        "means2d": means.new_zeros(num_b, num_c, num_n, 2),
        "depths": means.new_zeros(num_b, num_c, num_n),
        "radii": torch.zeros(num_b, num_c, num_n, 2, dtype=torch.int32, device=means.device),
        "n_visible": zeros_i,
        "n_intersections": zeros_i.clone(),
    }


@dataclass
class Renderer:
    """Renderer configuration (built by Hydra from conf/renderer/*.yaml); call it to render.

    Attributes:
        backend: "warp" (CPU + CUDA), "torch" (slow reference) or "gsplat" (CUDA only).
        tile_size: Screen tile side (px) for binning.
        num_threads: CPU threads that launch the warp raster kernels (2 cores here).
        near_plane: Near clipping depth (m).
        far_plane: Far clipping depth (m).
        eps2d: Screen-space dilation of 2D covariances (px^2); 0.3 as in 3DGS/gsplat.
    """

    backend: str = "warp"
    tile_size: int = 16
    num_threads: int = 2
    near_plane: float = 0.01
    far_plane: float = 1e10
    eps2d: float = 0.3

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {sorted(BACKENDS)}, got {self.backend!r}")

    def __call__(
        self,
        means: Tensor,  # [..., N, 3]
        quats: Tensor,  # [..., N, 4]
        scales: Tensor,  # [..., N, 3]
        opacities: Tensor,  # [..., N]
        colors: Tensor,  # [..., N, 3]
        viewmats: Tensor,  # [..., C, 4, 4]
        Ks: Tensor,  # [..., C, 3, 3]
        width: int,
        height: int,
        background: Tensor | None = None,  # [3] or [..., C, 3]
    ) -> tuple[Tensor, Tensor, dict]:
        """Same as `rasterize` with this object's options."""
        gauss, cams = (means, quats, scales, opacities, colors), (viewmats, Ks)
        return rasterize(*gauss, *cams, width, height, background, **asdict(self))
