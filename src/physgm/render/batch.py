"""`SplatBatch`: the Gaussians and cameras of one `rasterize` call, as every backend receives them."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor


@dataclass(frozen=True)
class SplatBatch:
    """B scenes, each with its own N Gaussians seen by its own C cameras.

    `rasterize` builds it once, after its checks, by flattening the leading dims "..." into B;
    a backend renders all B x C images of it with `backend(batch, settings)`.
    """

    means: Tensor  # [B, N, 3] world (m)
    quats: Tensor  # [B, N, 4] (w, x, y, z), any non-zero norm
    scales: Tensor  # [B, N, 3] linear std (m)
    opacities: Tensor  # [B, N] in [0, 1]
    colors: Tensor  # [B, N, 3] RGB
    viewmats: Tensor  # [B, C, 4, 4] world-to-camera, OpenCV
    Ks: Tensor  # [B, C, 3, 3] pixel intrinsics

    @property
    def num_b(self) -> int:
        return self.means.shape[0]

    @property
    def num_c(self) -> int:
        return self.viewmats.shape[1]

    @property
    def num_n(self) -> int:
        return self.means.shape[1]

    def gaussians(self) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """(means, quats, scales, opacities, colors): the inputs the images are differentiable in."""
        return self.means, self.quats, self.scales, self.opacities, self.colors
