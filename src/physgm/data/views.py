"""Choosing input and target views of an asset and turning them into training tensors.

Input views. Every example carries the 4-view input set; the collate function keeps the
first V = 1 or 4 of them for the whole batch:

* view 1 (the single-view input) is the *canonical* camera: elevation 0, azimuth 0 (the view
  ``rgba/000.png`` of synthetic assets, facing the object's +x side, lit from above-front);
* views 2-4 are the cameras closest to azimuth +90, +180, +270 degrees at the same elevation.

With ``random_azimuth`` (training only) view 1 is any view at the input elevation instead and
the other three follow it around the object. Cameras are found from their centres, so real
assets with other camera layouts work as long as they have views around the object.

Target views: the 4 input views plus ``num_targets - 4`` other views drawn at random, so the
targets always include whichever inputs the batch keeps.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from physgm.data.format import AssetError, PhysicalLabels
from physgm.data.priors import material_names
from physgm.model.cnn_encoder import ImageFeatures

NUM_INPUT_SET = 4  # size of the input set every example carries


@dataclass
class ViewConfig:
    """How examples are cut from an asset."""

    num_targets: int = 8  # target views per example (>= 4, includes the 4 input views)
    input_resolution: int | None = None  # square input size in px; None keeps the stored size
    target_resolution: int | None = None  # same for targets
    background: float = 1.0  # grey level the RGBA views are composited over (1 = white)
    random_azimuth: bool = False  # rotate the input set to a random starting view
    input_elevation_deg: float = 0.0  # elevation of the input views
    surface_points: int = 0  # ground-truth surface points per example (for loss.surface); 0: none

    def __post_init__(self) -> None:
        if self.num_targets < NUM_INPUT_SET:
            raise ValueError(
                f"num_targets must be at least {NUM_INPUT_SET} (the input set), got {self.num_targets}"
            )


class FeatureSource(Protocol):
    """Cached frozen-encoder features (``physgm.data.feature_cache.FeatureStore``)."""

    def load(self, asset_id: str, views: list[int]) -> ImageFeatures:  # [V, ...]
        ...


class AssetRecord(Protocol):
    """What the example builder needs from an asset, wherever it is stored."""

    id: str
    c2w: Tensor  # [C, 4, 4]
    Ks: Tensor  # [C, 3, 3]
    width: int
    height: int
    physical: PhysicalLabels

    def load_rgba(self, indices: list[int]) -> np.ndarray:  # [V, H, W, 4] float32 in [0, 1]
        ...

    def load_surface(self) -> np.ndarray | None:  # [N, 3] ground-truth Gaussian centres, or None
        ...


@dataclass
class Example:
    """One asset's tensors before batching (I = the 4-view input set, T = num_targets)."""

    id: str
    input_images: Tensor  # [I, 3, Hi, Wi]
    input_masks: Tensor  # [I, 1, Hi, Wi]
    input_c2w: Tensor  # [I, 4, 4]
    input_Ks: Tensor  # [I, 3, 3]
    input_index: Tensor  # [I] view numbers in the asset
    target_images: Tensor  # [T, 3, Ht, Wt]
    target_masks: Tensor  # [T, 1, Ht, Wt]
    target_c2w: Tensor  # [T, 4, 4]
    target_Ks: Tensor  # [T, 3, 3]
    target_index: Tensor  # [T]
    material: int  # annotated class
    true_material: int
    log10_E: float  # annotated
    nu: float  # annotated
    true_log10_E: float
    true_nu: float
    true_known: bool
    input_features: ImageFeatures | None = None  # [I, ...] cached frozen-encoder outputs of the inputs
    surface_points: Tensor | None = None  # [S, 3] ground-truth surface points (cfg.surface_points)


def view_directions(c2w: Tensor) -> np.ndarray:
    """Unit directions from the origin to each camera centre, [C, 3]."""
    centres = c2w[:, :3, 3].double().numpy()
    return centres / np.maximum(np.linalg.norm(centres, axis=1, keepdims=True), 1e-12)


def _direction(az_deg: float, el_deg: float) -> np.ndarray:
    az, el = math.radians(az_deg), math.radians(el_deg)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def ring_views(c2w: Tensor, elevation_deg: float) -> list[int]:
    """Views at the input elevation (within 1 degree; else the nearest elevation): where inputs come from."""
    dirs = view_directions(c2w)
    gap = np.abs(np.degrees(np.arcsin(np.clip(dirs[:, 2], -1, 1))) - elevation_deg)
    ring = np.flatnonzero(gap < 1.0)
    return [int(i) for i in (ring if len(ring) else np.flatnonzero(gap == gap.min()))]


def select_views(
    c2w: Tensor, cfg: ViewConfig, rng: np.random.Generator | None
) -> tuple[list[int], list[int]]:
    """Input set (4 views) and targets (num_targets views, inputs first) of one asset.

    Args:
        c2w: [C, 4, 4] cameras of the asset.
        cfg: view settings.
        rng: randomness for the extra targets and ``random_azimuth``.
    """
    n = c2w.shape[0]
    if n < cfg.num_targets:
        raise AssetError(f"asset has {n} views but {cfg.num_targets} target views are requested")
    dirs = view_directions(c2w)
    el = np.degrees(np.arcsin(np.clip(dirs[:, 2], -1, 1)))
    az = np.degrees(np.arctan2(dirs[:, 1], dirs[:, 0]))
    if cfg.random_azimuth and rng is not None:
        ring = ring_views(c2w, cfg.input_elevation_deg)
        first = ring[int(rng.integers(len(ring)))]
    else:
        first = int(np.argmax(dirs @ _direction(0.0, cfg.input_elevation_deg)))
    inputs = [first]
    for j in range(1, NUM_INPUT_SET):
        score = dirs @ _direction(az[first] + 90.0 * j, el[first])
        score[inputs] = -np.inf
        inputs.append(int(np.argmax(score)))
    rest = [i for i in range(n) if i not in inputs]
    extra = cfg.num_targets - NUM_INPUT_SET
    picks = (
        (rng.choice(len(rest), size=extra, replace=False) if rng is not None else np.arange(extra))
        if extra
        else []
    )
    return inputs, inputs + [rest[int(i)] for i in picks]


def composite_views(
    rgba: np.ndarray,  # [V, H, W, 4] straight alpha in [0, 1]
    Ks: Tensor,  # [V, 3, 3]
    size: int | None,
    background: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite over the background, resize; returns images [V,3,h,w], masks [V,1,h,w], Ks [V,3,3]."""
    t = torch.from_numpy(np.ascontiguousarray(rgba)).permute(0, 3, 1, 2).float()
    alpha = t[:, 3:]
    rgb = t[:, :3] * alpha + background * (1 - alpha)  # linear in alpha, so resizing after is exact
    Ks = Ks.clone().float()
    h, w = t.shape[-2:]
    if size is not None and (size != h or size != w):
        rgb = F.interpolate(rgb, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
        alpha = F.interpolate(alpha, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
        Ks[:, 0] *= size / w
        Ks[:, 1] *= size / h
    return rgb.clamp(0, 1), alpha.clamp(0, 1), Ks


def build_example(
    record: AssetRecord,
    cfg: ViewConfig,
    rng: np.random.Generator | None,
    features: FeatureSource | None = None,
) -> Example:
    """Cut one example (input set + targets + labels) from an asset; ``features``: a frozen-encoder cache."""
    inputs, targets = select_views(record.c2w, cfg, rng)
    # Decode each needed view once; inputs are the first four targets.
    rgba = record.load_rgba(targets)
    if rgba.shape[1:3] != (record.height, record.width):
        raise AssetError(
            f"views are {rgba.shape[2]}x{rgba.shape[1]} px but cameras.json says "
            f"{record.width}x{record.height}"
        )
    in_img, in_mask, in_K = composite_views(
        rgba[:NUM_INPUT_SET], record.Ks[inputs], cfg.input_resolution, cfg.background
    )
    tg_img, tg_mask, tg_K = composite_views(rgba, record.Ks[targets], cfg.target_resolution, cfg.background)
    phys = record.physical
    names = material_names()
    ann = phys.annotation
    return Example(
        id=record.id,
        input_images=in_img,
        input_masks=in_mask,
        input_c2w=record.c2w[inputs].float(),
        input_Ks=in_K,
        input_index=torch.tensor(inputs),
        target_images=tg_img,
        target_masks=tg_mask,
        target_c2w=record.c2w[targets].float(),
        target_Ks=tg_K,
        target_index=torch.tensor(targets),
        material=names.index(ann.material),
        true_material=names.index(phys.material),
        log10_E=math.log10(ann.E),
        nu=ann.nu,
        true_log10_E=math.log10(phys.E),
        true_nu=phys.nu,
        true_known=phys.true_known,
        input_features=features.load(record.id, inputs) if features is not None else None,
        surface_points=_surface_points(record, cfg.surface_points, rng),
    )


def _surface_points(record: AssetRecord, count: int, rng: np.random.Generator | None) -> Tensor | None:
    """``count`` of the asset's ground-truth Gaussian centres (None without them, or count 0):
    drawn by ``rng``, else evenly spaced through the file."""
    if count <= 0:
        return None
    points = record.load_surface()
    if points is None or len(points) == 0:
        return None
    if rng is not None:
        index = rng.choice(len(points), size=count, replace=len(points) < count)
    else:
        index = np.linspace(0, len(points) - 1, count).round().astype(np.int64)
    return torch.as_tensor(np.asarray(points[index], dtype=np.float32))


def example_rng(asset_id: str, deterministic: bool, seed: int = 0) -> np.random.Generator:
    """Fixed views per asset for evaluation; fresh draws (from torch's seeded RNG) for training."""
    if deterministic:
        return np.random.default_rng([seed, zlib.crc32(asset_id.encode())])
    return np.random.default_rng(int(torch.randint(0, 2**62, ())))


# What ``build_example`` raises on a damaged asset; PIL reports truncated PNGs as the last three.
LOAD_ERRORS = (AssetError, OSError, ValueError, SyntaxError)
