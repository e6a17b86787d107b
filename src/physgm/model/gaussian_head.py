"""DPT head: patch tokens from 4 backbone layers -> one 3D Gaussian per input pixel (or ``layers``).

The four token maps are reassembled at 4x, 2x, 1x and 1/2x the patch grid, fused coarse to fine
(DPT, Ranftl et al. 2021), upsampled to the input resolution and, concatenated with the input
image (and, with ``depth_prior="hull"``, the ray's visual-hull segment), decoded by a small conv
into raw per-pixel channels. ``GaussianActivations`` turns those into Gaussians: each one sits on
its pixel's camera ray at a predicted depth, plus a small free offset. Pixels outside the object
mask are kept in the batched tensors (so every sample has N = L * V * H * W rows) but flagged
invalid and given zero opacity.

With ``layers`` = L > 1 (not in the paper) every pixel gets L Gaussians on its ray: each layer
after the first has its own last 1x1 conv on the same hidden features, and its raw opacity is
shifted by ``layer_opacity_shift``, so a layer added to a trained model starts faint
and learns where it helps, such as the far side of an object seen from one view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from physgm.gaussians import Gaussians
from physgm.model.config import GaussianHeadConfig
from physgm.model.hull import hull_depth_range

# Raw output channels of the head, in order; activations live in GaussianActivations.forward.
RAW_CHANNELS = {"depth": 1, "offset": 3, "scale": 3, "quat": 4, "opacity": 1, "color": 3}
# "range": the paper's near + (far - near) * sigmoid; "centre": around the ray point nearest the
# scene origin; "hull": the sigmoid on the ray's segment inside the input masks' visual hull.
DEPTH_PRIORS = ("range", "centre", "hull")


@dataclass
class GaussianPrediction:
    """Batched per-pixel Gaussians, N = L * V * H * W (layer-major, then view-major, then row-major
    pixels).

    Attributes:
        means: [B, N, 3] centres = ray origin + depth * ray direction + offset.
        quats: [B, N, 4] unit quaternions (w, x, y, z).
        scales: [B, N, 3] linear standard deviations.
        opacities: [B, N] in [0, 1]; exactly 0 where ``valid`` is False.
        colors: [B, N, 3] RGB in [0, 1].
        depths: [B, N] distance along the unit pixel ray, in [near, far].
        valid: [B, N] bool, the input mask was above the threshold at this pixel.
        views, height, width, layers: the V, H, W and L that N unfolds into.
    """

    means: Tensor  # [B, N, 3]
    quats: Tensor  # [B, N, 4]
    scales: Tensor  # [B, N, 3]
    opacities: Tensor  # [B, N]
    colors: Tensor  # [B, N, 3]
    depths: Tensor  # [B, N]
    valid: Tensor  # [B, N] bool
    views: int
    height: int
    width: int
    layers: int = 1

    @property
    def count(self) -> Tensor:  # [B] int64
        """Number of valid (in-mask) Gaussians per sample."""
        return self.valid.sum(dim=1)

    def to_gaussians(self, b: int) -> Gaussians:
        """The valid Gaussians of sample ``b`` as a ``physgm.gaussians.Gaussians``."""
        keep = self.valid[b]
        return Gaussians(
            means=self.means[b][keep],
            quats=self.quats[b][keep],
            scales=self.scales[b][keep],
            opacities=self.opacities[b][keep],
            colors=self.colors[b][keep],
        )

    def detach(self) -> GaussianPrediction:
        return GaussianPrediction(
            **{
                f.name: v.detach() if isinstance(v := getattr(self, f.name), Tensor) else v
                for f in fields(self)
            }
        )


class GaussianActivations(nn.Module):
    """Maps raw head channels to Gaussian parameters; the only place output activations live."""

    def __init__(self, cfg: GaussianHeadConfig) -> None:
        super().__init__()
        if not 0 < cfg.near < cfg.far:
            raise ValueError(f"gaussian_head needs 0 < near < far, got near={cfg.near}, far={cfg.far}")
        if not 0 < cfg.scale_min < cfg.scale_max:
            raise ValueError(
                f"gaussian_head needs 0 < scale_min < scale_max, got {cfg.scale_min}, {cfg.scale_max}"
            )
        if cfg.depth_prior not in DEPTH_PRIORS:
            raise ValueError(
                f"gaussian_head.depth_prior must be one of {DEPTH_PRIORS}, got {cfg.depth_prior!r}"
            )
        if cfg.depth_prior == "centre" and not cfg.scene_radius > 0:
            raise ValueError(
                f"gaussian_head.scene_radius must be > 0 with depth_prior='centre', got {cfg.scene_radius}"
            )
        self.cfg = cfg
        self.register_buffer("quat_bias", torch.tensor([1.0, 0.0, 0.0, 0.0]), persistent=False)

    def forward(
        self,
        raw: dict[str, Tensor],  # name -> [..., RAW_CHANNELS[name]]
        rgb: Tensor,  # [..., 3] input pixel colour in [0, 1]
        origins: Tensor,  # [..., 3] ray origins
        directions: Tensor,  # [..., 3] unit ray directions
        depth_range: tuple[Tensor, Tensor] | None = None,  # ([..., 1], [..., 1]) with depth_prior="hull"
        opacity_shift: float = 0.0,  # added to the raw opacity (layers after the first)
    ) -> dict[str, Tensor]:
        c = self.cfg
        if c.depth_prior == "hull":
            if depth_range is None:
                raise ValueError("depth_prior='hull' needs the per-ray depth_range from physgm.model.hull")
            lo, hi = depth_range
            depth = lo + (hi - lo) * torch.sigmoid(
                raw["depth"]
            )  # [..., 1], the paper's sigmoid on the hull segment
        elif c.depth_prior == "centre":
            # distance along the unit ray to the point closest to the scene origin (object centre)
            centre = -(origins * directions).sum(dim=-1, keepdim=True)
            depth = (centre + c.scene_radius * torch.tanh(raw["depth"])).clamp(c.near, c.far)  # [..., 1]
        else:
            depth = c.near + (c.far - c.near) * torch.sigmoid(raw["depth"])  # [..., 1], inside [near, far]
        offset = c.max_offset * torch.tanh(raw["offset"])  # bounded so Gaussians stay near their ray
        log_lo, log_hi = math.log(c.scale_min), math.log(c.scale_max)
        scale = torch.exp(log_lo + (log_hi - log_lo) * torch.sigmoid(raw["scale"]))  # log-uniform range
        # Bias towards the identity rotation so a zero output is a valid unit quaternion.
        quat = F.normalize(raw["quat"] + self.quat_bias, dim=-1, eps=1e-6)
        opacity = torch.sigmoid(raw["opacity"][..., 0] + opacity_shift)
        # Residual on the input colour in logit space: a zero output reproduces the pixel colour.
        color = torch.sigmoid(raw["color"] + torch.logit(rgb.clamp(0.0, 1.0), eps=1e-3))
        means = origins + depth * directions + offset
        return {
            "means": means,
            "quats": quat,
            "scales": scale,
            "opacities": opacity,
            "colors": color,
            "depths": depth[..., 0],
        }


class _ResidualConv(nn.Module):
    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:  # [B, C, h, w] -> same
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class _Fusion(nn.Module):
    """Adds a skip map to the coarser path, refines it and resizes to the next finer map."""

    def __init__(self, channels: int, has_skip: bool) -> None:
        super().__init__()
        self.skip = _ResidualConv(channels) if has_skip else None
        self.refine = _ResidualConv(channels)
        self.out = nn.Conv2d(channels, channels, 1)

    def forward(self, x: Tensor, skip: Tensor | None, size: tuple[int, int]) -> Tensor:
        if self.skip is not None:
            x = x + self.skip(skip)
        x = F.interpolate(self.refine(x), size=size, mode="bilinear", align_corners=False)
        return self.out(x)


class DPTHead(nn.Module):
    """Dense prediction head on 4 token layers; see the module docstring."""

    def __init__(
        self, cfg: GaussianHeadConfig, dim: int, patch_size: int, skip_channels: tuple[int, ...] | None = None
    ) -> None:
        super().__init__()
        if len(cfg.layer_channels) != 4:
            raise ValueError(f"gaussian_head.layer_channels needs 4 entries, got {list(cfg.layer_channels)}")
        self.patch_size = patch_size
        ch = cfg.layer_channels
        self.norms = nn.ModuleList(nn.LayerNorm(dim) for _ in range(4))
        self.projects = nn.ModuleList(nn.Conv2d(dim, c, 1) for c in ch)
        # Reassemble into a pyramid: 4x, 2x, 1x and 1/2x the patch grid.
        self.resamples = nn.ModuleList(
            [
                nn.ConvTranspose2d(ch[0], ch[0], kernel_size=4, stride=4),
                nn.ConvTranspose2d(ch[1], ch[1], kernel_size=2, stride=2),
                nn.Identity(),
                nn.Conv2d(ch[3], ch[3], kernel_size=3, stride=2, padding=1),
            ]
        )
        self.to_features = nn.ModuleList(nn.Conv2d(c, cfg.features, 3, padding=1, bias=False) for c in ch)
        # A frozen CNN encoder's pyramid (strides 4, 8, 16, 32 = this pyramid's levels with patch
        # size 16) joins each level: the fine levels see image detail the tokens have pooled away.
        self.encoder_skips = (
            nn.ModuleList(nn.Conv2d(c, cfg.features, 1) for c in skip_channels) if skip_channels else None
        )
        self.fusions = nn.ModuleList(_Fusion(cfg.features, has_skip=i < 3) for i in range(4))
        self.pre_upsample = nn.Conv2d(cfg.features, cfg.features // 2, 3, padding=1)
        out_channels = sum(RAW_CHANNELS.values())
        # + input RGB for sharp detail; + the hull segment (start, length) with depth_prior="hull"
        self.takes_hull = cfg.depth_prior == "hull"
        self.output = nn.Sequential(
            nn.Conv2d(cfg.features // 2 + 3 + 2 * self.takes_hull, cfg.hidden, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(cfg.hidden, out_channels, 1),
        )
        # The last 1x1 conv of each further layer (cfg.layers - 1 of them), on the same hidden features.
        if cfg.layers < 1:
            raise ValueError(f"gaussian_head.layers must be at least 1, got {cfg.layers}")
        self.layer_outputs = nn.ModuleList(
            nn.Conv2d(cfg.hidden, out_channels, 1) for _ in range(cfg.layers - 1)
        )
        # Small last layers: at init every Gaussian sits mid-range on its ray with the pixel's colour.
        for last in [self.output[-1], *self.layer_outputs]:
            nn.init.normal_(last.weight, std=1e-3)
            nn.init.zeros_(last.bias)

    def forward(
        self,
        tokens: list[Tensor],  # 4 x [B', h * w, D], fine to coarse backbone layers
        images: Tensor,  # [B', 3, H, W] in [0, 1]
        guide: Tensor | None = None,  # [B', 2, H, W] hull segment start and length (depth_prior="hull")
        skips: list[Tensor] | None = None,  # 4 x [B', C_i, H / s_i, W / s_i] encoder maps, fine to coarse
    ) -> list[dict[str, Tensor]]:  # per layer: name -> [B', H, W, RAW_CHANNELS[name]]
        height, width = images.shape[-2:]
        h, w = height // self.patch_size, width // self.patch_size
        if (skips is not None) != (self.encoder_skips is not None):
            raise ValueError(
                "the DPT head takes encoder skip maps exactly when it was built with skip_channels"
            )
        maps = []
        for i, t in enumerate(tokens):
            x = self.norms[i](t).transpose(1, 2).reshape(t.shape[0], -1, h, w)  # [B', D, h, w]
            x = self.to_features[i](self.resamples[i](self.projects[i](x)))
            if skips is not None:
                x = x + self.encoder_skips[i](skips[i].to(x.dtype))
            maps.append(x)
        x = self.fusions[3](maps[3], None, maps[2].shape[-2:])
        x = self.fusions[2](x, maps[2], maps[1].shape[-2:])
        x = self.fusions[1](x, maps[1], maps[0].shape[-2:])
        x = self.fusions[0](x, maps[0], maps[0].shape[-2:])
        x = F.interpolate(self.pre_upsample(x), size=(height, width), mode="bilinear", align_corners=False)
        if (guide is not None) != self.takes_hull:
            raise ValueError("the DPT head takes the hull guide exactly when depth_prior='hull'")
        extra = [images * 2.0 - 1.0] + ([guide] if guide is not None else [])
        hidden = self.output[:-1](torch.cat([x, *extra], dim=1))  # [B', hidden, H, W]
        layers = []
        for last in [self.output[-1], *self.layer_outputs]:
            raw = last(hidden).permute(0, 2, 3, 1)  # [B', H, W, C]
            layers.append(
                dict(zip(RAW_CHANNELS, raw.split(list(RAW_CHANNELS.values()), dim=-1), strict=True))
            )
        return layers

    def layer_sources(self) -> dict[str, str]:
        """Each further layer's weight name -> the first layer's weight it starts as (names within
        the head): a model with one layer hands its output conv to each added one."""
        return {
            f"layer_outputs.{j}.{key}": f"output.{len(self.output) - 1}.{key}"
            for j in range(len(self.layer_outputs))
            for key in ("weight", "bias")
        }


class GaussianHead(nn.Module):
    """DPT head + activations + masking: tokens and rays -> ``GaussianPrediction``."""

    def __init__(
        self, cfg: GaussianHeadConfig, dim: int, patch_size: int, skip_channels: tuple[int, ...] | None = None
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.dpt = DPTHead(cfg, dim, patch_size, skip_channels)
        self.activations = GaussianActivations(cfg)

    def forward(
        self,
        tokens: list[Tensor],  # 4 x [B * V, h * w, D]
        images: Tensor,  # [B, V, 3, H, W] in [0, 1]
        masks: Tensor,  # [B, V, 1, H, W] in [0, 1]
        c2w: Tensor,  # [B, V, 4, 4] OpenCV camera-to-world
        Ks: Tensor,  # [B, V, 3, 3]
        directions: Tensor,  # [B, V, H, W, 3] unit pixel-ray directions
        skips: list[Tensor] | None = None,  # 4 x [B * V, C_i, H / s_i, W / s_i] frozen encoder maps
    ) -> GaussianPrediction:
        b, v, _, height, width = images.shape
        c = self.cfg
        guide, depth_range = None, None
        if c.depth_prior == "hull":
            lo, hi = hull_depth_range(
                masks, c2w, Ks, directions, c.near, c.far, c.hull_samples, c.mask_threshold
            )
            span = c.far - c.near
            guide = torch.stack([(lo - c.near) / span, (hi - lo) / span], dim=2).flatten(
                0, 1
            )  # [B*V, 2, H, W]
            depth_range = (lo.reshape(b, -1, 1), hi.reshape(b, -1, 1))
        rgb = images.permute(0, 1, 3, 4, 2).reshape(b, -1, 3)
        dirs = directions.reshape(b, -1, 3)
        origins = c2w[:, :, None, :3, 3].to(dirs).expand(b, v, height * width, 3).reshape(b, -1, 3)
        layers = []
        for i, raw in enumerate(self.dpt(tokens, images.flatten(0, 1), guide, skips)):
            raw = {k: r.reshape(b, v * height * width, -1) for k, r in raw.items()}  # [B, V * H * W, c]
            shift = c.layer_opacity_shift if i else 0.0
            layers.append(self.activations(raw, rgb, origins, dirs, depth_range, shift))
        out = {k: torch.cat([layer[k] for layer in layers], dim=1) for k in layers[0]}  # [B, N, ...]
        valid = (masks.reshape(b, -1) > self.cfg.mask_threshold).repeat(1, len(layers))  # [B, N]
        # Zero opacity outside the mask keeps batched rendering exact without ragged tensors.
        out["opacities"] = out["opacities"] * valid
        return GaussianPrediction(**out, valid=valid, views=v, height=height, width=width, layers=len(layers))
