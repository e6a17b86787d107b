"""Constants and per-call settings shared by every rasterisation backend.

The thresholds are those of 3DGS / gsplat; every backend must use exactly these values so the
fast ones can be compared with the torch reference to 1e-4.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch

ALPHA_MIN = 1.0 / 255.0  # a Gaussian whose alpha at a pixel is below this is skipped there
ALPHA_MAX = 0.99  # alpha is clamped here so transmittance never reaches exactly 0
T_MIN = 1e-4  # a pixel stops compositing before the Gaussian that would push T below this
FOV_CLAMP = 0.3  # EWA Jacobian directions are clamped to 0.3 tan(half FOV) beyond the border
EXTENT_MARGIN_REL = 1e-3  # bounding boxes are grown a little so float rounding never drops a
EXTENT_MARGIN_ABS = 1e-3  # pixel that still passes the alpha test (the box is only a speed-up)
# The Warp raster kernels skip a pair before exp when q = d^T Sigma^-1 d > 2 ln(255 o) + this
# margin; the margin keeps that pre-test strictly looser than the exact alpha test.
QMAX_MARGIN = 1e-3


@dataclass(frozen=True)
class RasterSettings:
    """Options of one `rasterize` call after validation.

    Attributes:
        width: Image width in pixels.
        height: Image height in pixels.
        near_plane: Gaussians with camera depth below this (m) are culled.
        far_plane: Gaussians with camera depth above this (m) are culled.
        eps2d: Screen-space dilation (px^2) added to the diagonal of every 2D covariance.
        tile_size: Side of the square screen tiles used for binning (px).
        num_threads: Python threads that launch CPU raster kernels in parallel (warp backend).
        warp_layout: Warp raster kernels: "tile" (a thread per tile, 16-pixel SIMD rows, fast
            on CPU; tiles of at most 16 px), "pixel" (a thread per pixel, for CUDA) or "auto"
            (tile on CPU when tile_size <= 16, else pixel).
        warp_binning: How entries reach (image, tile, depth) order: "counting" (pairs sorted by
            depth, then appended to their tiles in one serial launch; CPU only), "sort" (a
            global sort of (tile, depth) keys; any device) or "auto" (counting on CPU).
    """

    width: int
    height: int
    near_plane: float = 0.01
    far_plane: float = 1e10
    eps2d: float = 0.3
    tile_size: int = 16
    num_threads: int = 2
    warp_layout: str = "auto"
    warp_binning: str = "auto"

    def __post_init__(self) -> None:
        # Both binnings order pairs by the bits of their (positive) depth.
        if not 0.0 < self.near_plane < self.far_plane:
            raise ValueError(
                "near_plane and far_plane must satisfy 0 < near_plane < far_plane (m), got "
                f"near_plane={self.near_plane}, far_plane={self.far_plane}"
            )
        if self.warp_binning not in ("auto", "counting", "sort"):
            raise ValueError(f"warp_binning must be 'auto', 'counting' or 'sort', got {self.warp_binning!r}")
        if self.warp_layout not in ("auto", "tile", "pixel"):
            raise ValueError(f"warp_layout must be 'auto', 'tile' or 'pixel', got {self.warp_layout!r}")

    @property
    def tiles_x(self) -> int:
        return (self.width + self.tile_size - 1) // self.tile_size

    @property
    def tiles_y(self) -> int:
        return (self.height + self.tile_size - 1) // self.tile_size


@contextmanager
def single_threaded_torch() -> Iterator[None]:
    """Runs the enclosed torch ops on one intra-op thread, then restores the setting.

    The warp backend's torch glue (sort, cumsum, gathers, checks) works on arrays of ~1e4-1e5
    elements. With two OpenMP threads on a 2-core machine that other processes also use, each
    such op can stall for a whole scheduler slice, so the glue runs serially; the heavy work is
    parallel in the raster kernels.
    """
    previous = torch.get_num_threads()
    if previous == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
