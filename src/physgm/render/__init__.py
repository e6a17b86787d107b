"""Gaussian-splatting renderer: `rasterize(...)` with warp (CPU/CUDA), torch and gsplat backends.

`Renderer` is the small config object Hydra builds from conf/renderer/*.yaml.
"""

from physgm.render.api import BACKENDS, Renderer, rasterize, rasterize_gaussians
from physgm.render.settings import RasterSettings

__all__ = ["BACKENDS", "RasterSettings", "Renderer", "rasterize", "rasterize_gaussians"]
