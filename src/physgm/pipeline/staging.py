"""Putting the object into the world: physical size, ground contact, and an output camera that
looks at the scene from the input view's direction and keeps the whole motion in frame.

The model's Gaussians live in a normalised object frame (centre at the origin, radius ~0.5,
+z up). ``place_object`` scales them so the largest extent is the configured physical size and
sets them on the ground; the scene (conf/sim/scene) then lifts or moves them as it requires.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch

from physgm.cameras import Cameras, intrinsics_from_fov, look_at
from physgm.errors import UserError
from physgm.gaussians import Gaussians
from physgm.placement import Placement, place

OUTLIER_QUANTILE = 0.001  # the extent ignores this share of stray Gaussians on each side
CLIP_SHARE = 0.98  # the output camera keeps this share of a run's particles in view (``clip_region``)


def place_object(g: Gaussians, size_m: float, ground: float, min_opacity: float) -> Placement:
    """Scale ``g`` to a largest extent of ``size_m``, centred over the origin, lowest point at ``ground``."""
    keep = g.opacities >= min_opacity
    if not bool(keep.any()):
        raise UserError(
            f"no Gaussian is opaque enough (opacity >= {min_opacity:.3g}) to form an object; check the input"
        )
    pts = g.means[keep].double()
    if len(pts) > 1:
        lo = torch.quantile(pts, OUTLIER_QUANTILE, dim=0)
        hi = torch.quantile(pts, 1 - OUTLIER_QUANTILE, dim=0)
    else:
        lo = hi = pts[0]
    extent = float((hi - lo).max())
    if not math.isfinite(extent) or extent <= 1e-9:
        raise UserError(
            f"the object has no size (extent {extent:.3g}); the input holds a single point or non-finite "
            "Gaussians"
        )
    middle = (lo + hi) / 2
    return place(g, size_m / extent, (middle[0], middle[1], lo[2]), (0.0, 0.0, ground))


# -- the region each scene's motion can cover ------------------------------------------------
Region = tuple[np.ndarray, np.ndarray]


def _drop_region(lo: np.ndarray, hi: np.ndarray, cfg: dict) -> Region:
    size = float((hi - lo).max())
    spread = np.array([0.25 * size, 0.25 * size, 0.0])  # soft objects splat sideways on impact
    top = hi.copy()
    top[2] += float(cfg.get("height", 0.0))
    return lo - spread, top + spread


def _stretch_region(lo: np.ndarray, hi: np.ndarray, cfg: dict) -> Region:
    a, ratio = int(cfg["axis"]), float(cfg["ratio"])
    grow = np.zeros(3)
    grow[a] = 0.5 * (ratio - 1.0) * (hi[a] - lo[a])
    return lo - grow, hi + grow


def _push_region(lo: np.ndarray, hi: np.ndarray, cfg: dict) -> Region:
    a = int(cfg["axis"])
    size = float((hi - lo).max())
    lift = np.array([0.0, 0.0, float(cfg.get("lift", 0.0))])
    lo2, hi2 = lo + lift, hi + lift
    hi2[a] += float(cfg["wall_gap"])  # the wall stops it
    lo2[a] -= 0.25 * size  # rebound
    return lo2, hi2


REGIONS: dict[str, Callable[[np.ndarray, np.ndarray, dict], Region]] = {
    "drop": _drop_region,
    "stretch": _stretch_region,
    "push": _push_region,
}


def clip_region(
    lo: np.ndarray, hi: np.ndarray, positions: list[np.ndarray], share: float = CLIP_SHARE
) -> Region:
    """``lo``..``hi`` grown to hold what the simulations did: in every frame of every run, the middle
    ``share`` of its particles along each axis (``positions``: one [T, P, 3] array per run, m).

    The camera is framed on the region a scene's motion was planned in before anything ran; a body
    that bounces or rolls out of it (a ball, on the grid that follows it) would leave the frame.
    Framed on this region instead, it stays in view, while a few splashed particles cannot pull the
    camera far out. A region the runs stayed inside comes back unchanged; the pipeline reframes only
    when the grown one leaves the planned camera's image (``box_in_view``)."""
    if not 0.0 < share <= 1.0:
        raise ValueError(f"share={share!r} must be in (0, 1]")
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    q = (1.0 - share) / 2.0
    for x in positions:
        low, high = np.quantile(np.asarray(x, np.float64), [q, 1.0 - q], axis=1)  # [T, 3] each
        lo = np.minimum(lo, low.min(0))
        hi = np.maximum(hi, high.max(0))
    return lo, hi


def box_in_view(camera: Cameras, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Every corner of the box ``lo``..``hi`` (m) in front of ``camera`` and inside its image."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    vm = camera.viewmats[0].double().numpy()
    p = corners @ vm[:3, :3].T + vm[:3, 3]
    if not bool((p[:, 2] > 0.0).all()):
        return False
    uvw = p @ camera.Ks[0].double().numpy().T
    u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
    return bool(((u >= 0.0) & (u <= camera.width) & (v >= 0.0) & (v <= camera.height)).all())


def opaque_bounds(g: Gaussians, min_opacity: float) -> Region:
    """Box (lo [3], hi [3], m) of the centres of the Gaussians that carry mass."""
    pts = g.means[g.opacities >= min_opacity].double().numpy()
    return pts.min(0), pts.max(0)


def motion_region(lo: np.ndarray, hi: np.ndarray, scene: str, scene_cfg: dict) -> Region:
    """Box (lo [3], hi [3], m) the object can move through in ``scene``, from its rest bounds
    (``opaque_bounds`` of its placement)."""
    fn = REGIONS.get(scene)
    return fn(lo, hi, scene_cfg) if fn is not None else (lo, hi)


def direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector from the target towards a camera at this azimuth/elevation (cameras.py convention)."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def framing_camera(
    lo: np.ndarray,  # [3] m
    hi: np.ndarray,  # [3] m
    azimuth_deg: float,
    elevation_deg: float,
    fov_deg: float,
    width: int,
    height: int,
    margin: float,
) -> Cameras:
    """The camera looking at the box centre from (azimuth, elevation), just far enough that every
    box corner lies inside the central 1 / margin of the image."""
    d = direction(azimuth_deg, elevation_deg)
    target = (lo + hi) / 2
    basis = look_at(torch.from_numpy(target + d)[None], torch.from_numpy(target)[None])[0, :3, :3].numpy()
    right, down, forward = basis[:, 0], basis[:, 1], basis[:, 2]
    corners = (
        np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]) - target
    )
    tan_x = math.tan(math.radians(fov_deg) / 2)
    tan_y = tan_x * height / width
    # Corner p seen from eye = target + D d: depth p.forward + D, offsets p.right and p.down.
    need_x = np.abs(corners @ right) * margin / tan_x - corners @ forward
    need_y = np.abs(corners @ down) * margin / tan_y - corners @ forward
    size = float(np.linalg.norm(hi - lo))
    dist = max(float(need_x.max()), float(need_y.max()), 0.5 * size, 1e-3)
    eye = torch.from_numpy(target + dist * d)[None]
    c2w = look_at(eye, torch.from_numpy(target)[None]).float()
    return Cameras(c2w, intrinsics_from_fov(fov_deg, width, height)[None], width, height)


def floor_image(
    camera: Cameras,
    ground: float,
    tile_m: float,
    background: np.ndarray,  # [3]
    supersample: int = 2,
) -> np.ndarray:  # [H, W, 3]
    """Background with a checkered ground plane z = ``ground``, fading into the background with distance.

    Any point above the plane is nearer to the camera than the plane along a downward ray, so
    compositing the object over this image occludes correctly without a depth test.
    """
    w, h, s = camera.width, camera.height, supersample
    K = camera.Ks[0].double().numpy()
    c2w = camera.c2w[0].double().numpy()
    u = (np.arange(w * s) + 0.5) / s
    v = (np.arange(h * s) + 0.5) / s
    uu, vv = np.meshgrid(u, v)
    rays = (
        np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], -1) @ c2w[:3, :3].T
    )
    origin = c2w[:3, 3]
    down = rays[..., 2] < -1e-9
    t = np.where(down, (ground - origin[2]) / np.where(down, rays[..., 2], -1.0), np.inf)
    hit = origin + rays * np.where(np.isfinite(t), t, 0.0)[..., None]
    checker = (np.floor(hit[..., 0] / tile_m) + np.floor(hit[..., 1] / tile_m)) % 2
    shade = np.where(checker > 0, 0.78, 0.86)[..., None] * np.array([1.0, 1.0, 1.0])
    dist = np.linalg.norm(hit[..., :2] - origin[:2], axis=-1)
    fade = np.where(down, np.exp(-dist / (40.0 * tile_m)), 0.0)[..., None]
    img = fade * shade + (1 - fade) * background
    return img.reshape(h, s, w, s, 3).mean(axis=(1, 3)).astype(np.float32)
