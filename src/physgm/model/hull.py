"""Visual-hull depth range of every input pixel ray, from the input views' object masks.

A point can be on the object only if every input view sees it inside the object mask. Along each
pixel ray of each input view, the first and last such points bound where the object surface can
be; ``depth_prior="hull"`` (``physgm.model.gaussian_head``) puts the paper's near-far sigmoid on
that segment instead of on [near, far]. With one view the segment is the whole [near, far] (a
view's own mask contains all of its in-mask rays), so the prior reduces to the paper's.

Two passes per ray, both in closed form or vectorised over rays:

1. Clip the ray against every view's frustum through its mask's bounding box (four planes per
   view, exact): the hull lies inside that convex polyhedron, so only this segment is searched.
2. Test ``samples`` evenly spaced points of the segment against every mask (the pixel a point
   falls in); the first and last point inside all of them, widened by one spacing so sampling
   never cuts the surface off, give the range. A Warp kernel (``hull_kernels``) walks each ray
   from both ends and stops at the first hit; ``_hull_segment_torch`` is its twin for tests.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import warp as wp
from torch import Tensor

from physgm.cameras import invert_rigid
from physgm.model.hull_kernels import hull_segment_kernel
from physgm.warp_runtime import ensure_loaded

# Rays per chunk of the torch twin: its temporaries hold RAY_CHUNK * samples * V projected points
# (peak 120 MB at 32 samples and 4 views, measured), whatever the image size.
RAY_CHUNK = 1 << 14

# pass 2 for one scene: (origin [R, 3], direction [R, 3], proj [V, 3, 4], boxes [V, 4],
# masks [V, H, W] bool, samples, near, far) -> lo, hi [R]
SegmentSearch = Callable[[Tensor, Tensor, Tensor, Tensor, Tensor, int, float, float], tuple[Tensor, Tensor]]


@torch.no_grad()
def hull_depth_range(
    masks: Tensor,  # [B, V, 1, H, W] object mask in [0, 1]
    c2w: Tensor,  # [B, V, 4, 4] OpenCV camera-to-world
    Ks: Tensor,  # [B, V, 3, 3] pixel intrinsics
    directions: Tensor,  # [B, V, H, W, 3] unit pixel-ray directions (world)
    near: float,
    far: float,
    samples: int = 32,
    threshold: float = 0.1,
) -> tuple[Tensor, Tensor]:  # lo, hi: [B, V, H, W] depth along the unit ray
    """Where each input pixel ray runs inside the visual hull of the V masks (mask > threshold).

    Only rays of in-mask pixels are computed; the others, every ray when V = 1, and rays that no
    other view confirms (mask noise) get [near, far]. Points behind a camera or outside its image
    count as outside: the object is assumed in frame in every view.
    """
    return _hull_depth_range(masks, c2w, Ks, directions, near, far, samples, threshold)


def _hull_depth_range_torch(*args, **kwargs) -> tuple[Tensor, Tensor]:
    """``hull_depth_range`` with the plain-torch pass 2 (the kernel's twin, for tests)."""
    return _hull_depth_range(*args, **kwargs, search=_hull_segment_torch)


def _hull_depth_range(
    masks: Tensor,  # [B, V, 1, H, W]
    c2w: Tensor,  # [B, V, 4, 4]
    Ks: Tensor,  # [B, V, 3, 3]
    directions: Tensor,  # [B, V, H, W, 3]
    near: float,
    far: float,
    samples: int = 32,
    threshold: float = 0.1,
    search: SegmentSearch | None = None,  # pass 2; None: the Warp kernel's
) -> tuple[Tensor, Tensor]:  # lo, hi: [B, V, H, W]
    search = search or _hull_segment
    if samples < 2:
        raise ValueError(f"hull_samples must be at least 2, got {samples}")
    b, v, _, height, width = masks.shape
    dtype, device = directions.dtype, directions.device
    lo = torch.full((b, v, height, width), near, dtype=dtype, device=device)
    hi = torch.full_like(lo, far)
    if v == 1:
        return lo, hi
    inside_mask = masks[:, :, 0] > threshold  # [B, V, H, W]
    w2c = invert_rigid(c2w.to(dtype))  # [B, V, 4, 4]
    # P = K [R | t]: pixel (u, v) of a world point X is (P0 X / P2 X, P1 X / P2 X).
    proj = Ks.to(dtype) @ w2c[:, :, :3, :]  # [B, V, 3, 4]
    for i in range(b):  # one scene at a time: its in-mask rays are gathered without padding
        sel = inside_mask[i]  # [V, H, W]
        origin = c2w[i, :, None, None, :3, 3].to(dtype).expand(v, height, width, 3)[sel]  # [R, 3]
        direction = directions[i][sel]  # [R, 3]
        if origin.shape[0]:
            lo[i][sel], hi[i][sel] = search(
                origin, direction, proj[i], _mask_boxes(sel), sel, samples, near, far
            )
    return lo, hi


def _hull_segment(
    origin: Tensor,  # [R, 3]
    direction: Tensor,  # [R, 3] unit
    proj: Tensor,  # [V, 3, 4] K [R | t] of the scene's views
    boxes: Tensor,  # [V, 4] mask boxes (``_mask_boxes``)
    masks: Tensor,  # [V, H, W] bool
    samples: int,
    near: float,
    far: float,
) -> tuple[Tensor, Tensor]:  # lo, hi: [R]
    """Passes 1 and 2 of the module docstring for one scene's rays, pass 2 in the Warp kernel
    (float32; the result comes back in ``origin``'s dtype)."""
    t0, t1 = _clip_to_mask_frusta(origin, direction, proj, boxes, near, far)
    f32 = torch.float32
    fraction = torch.linspace(0.0, 1.0, samples, dtype=f32, device=origin.device)  # [K], as the twin's
    lo = torch.empty(origin.shape[0], dtype=f32, device=origin.device)
    hi = torch.empty_like(lo)
    wp.init()  # no-op after the first call
    device = wp.device_from_torch(origin.device)
    stream = wp.stream_from_torch(origin.device) if origin.device.type == "cuda" else None
    ensure_loaded(hull_segment_kernel, device)
    inputs = [
        wp.from_torch(origin.to(f32).contiguous(), dtype=wp.vec3),
        wp.from_torch(direction.to(f32).contiguous(), dtype=wp.vec3),
        wp.from_torch(t0.to(f32).contiguous()),
        wp.from_torch(t1.to(f32).contiguous()),
        wp.from_torch(fraction),
        wp.from_torch(proj.to(f32).contiguous()),
        wp.from_torch(masks.to(torch.uint8).contiguous()),
        near,
        far,
        wp.from_torch(lo),
        wp.from_torch(hi),
    ]
    wp.launch(hull_segment_kernel, dim=origin.shape[0], inputs=inputs, device=device, stream=stream)
    return lo.to(origin.dtype), hi.to(origin.dtype)


def _hull_segment_torch(origin: Tensor, direction: Tensor, *scene) -> tuple[Tensor, Tensor]:
    """The twin of ``_hull_segment`` (plain torch, every sample against every view): the arguments
    of ``_hull_chunk_torch``, run RAY_CHUNK rays at a time."""
    parts = [
        _hull_chunk_torch(origin[k : k + RAY_CHUNK], direction[k : k + RAY_CHUNK], *scene)
        for k in range(0, origin.shape[0], RAY_CHUNK)
    ]
    return torch.cat([part[0] for part in parts]), torch.cat([part[1] for part in parts])


def _hull_chunk_torch(
    origin: Tensor,  # [R, 3]
    direction: Tensor,  # [R, 3] unit
    proj: Tensor,  # [V, 3, 4]
    boxes: Tensor,  # [V, 4]
    masks: Tensor,  # [V, H, W] bool
    samples: int,
    near: float,
    far: float,
) -> tuple[Tensor, Tensor]:  # lo, hi: [R]
    v, height, width = masks.shape
    t0, t1 = _clip_to_mask_frusta(origin, direction, proj, boxes, near, far)
    fraction = torch.linspace(0.0, 1.0, samples, dtype=origin.dtype, device=origin.device)  # [K]
    t = t0[:, None] + (t1 - t0)[:, None] * fraction  # [R, K]
    points = origin[:, None] + t[..., None] * direction[:, None]  # [R, K, 3]
    homo = points.reshape(-1, 3) @ proj[:, :, :3].transpose(1, 2) + proj[:, None, :, 3]  # [V, R * K, 3]
    depth = homo[..., 2]
    col = (homo[..., 0] / depth.clamp_min(1e-9)).floor()
    row = (homo[..., 1] / depth.clamp_min(1e-9)).floor()
    in_frame = (depth > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    pixel = (row.clamp(0, height - 1) * width + col.clamp(0, width - 1)).long()  # [V, R * K]
    inside = (masks.reshape(v, -1).gather(1, pixel) & in_frame).all(dim=0).reshape(-1, samples)  # [R, K]
    found = inside.any(dim=-1) & (t1 > t0)
    first = inside.int().argmax(dim=-1)  # first True (0 when none)
    last = samples - 1 - inside.flip(-1).int().argmax(dim=-1)
    spacing = (t1 - t0) / (samples - 1)
    rows = torch.arange(t.shape[0], device=t.device)
    lo = torch.where(found, t[rows, first] - spacing, near).clamp(near, far)
    hi = torch.where(found, t[rows, last] + spacing, far).clamp(near, far)
    return lo, hi


def _mask_boxes(masks: Tensor) -> Tensor:  # [V, 4] (u0, u1, v0, v1) pixel edges
    """Bounding box of each view's mask in pixel-edge coordinates (an empty mask gives an empty box)."""
    v, height, width = masks.shape
    cols = torch.arange(width, device=masks.device, dtype=torch.float32)
    rows = torch.arange(height, device=masks.device, dtype=torch.float32)
    any_col, any_row = masks.any(dim=1), masks.any(dim=2)  # [V, W], [V, H]
    big = float(max(width, height) + 1)
    u0 = torch.where(any_col, cols, big).amin(dim=1)
    u1 = torch.where(any_col, cols + 1, -big).amax(dim=1)
    v0 = torch.where(any_row, rows, big).amin(dim=1)
    v1 = torch.where(any_row, rows + 1, -big).amax(dim=1)
    return torch.stack([u0, u1, v0, v1], dim=1)


def _clip_to_mask_frusta(
    origin: Tensor,  # [R, 3]
    direction: Tensor,  # [R, 3]
    proj: Tensor,  # [V, 3, 4] K [R | t]
    boxes: Tensor,  # [V, 4] (u0, u1, v0, v1)
    near: float,
    far: float,
) -> tuple[Tensor, Tensor]:  # t0, t1: [R]; t0 > t1 when the ray misses a frustum
    """The part of each ray inside every view's frustum through its mask box, within [near, far].

    u >= u0 in front of the camera is the half-space P0 X - u0 P2 X >= 0, linear in X; along the
    ray it is a + s t >= 0, which bounds t from below (s > 0) or above (s < 0). The same for
    u <= u1, v >= v0, v <= v1, and P2 X > 0 (in front of the camera).
    """
    u0, u1, v0, v1 = boxes.to(origin).unbind(dim=1)  # [V] each
    p0, p1, p2 = proj.unbind(dim=1)  # [V, 4] each
    planes = torch.stack(
        [p0 - u0[:, None] * p2, u1[:, None] * p2 - p0, p1 - v0[:, None] * p2, v1[:, None] * p2 - p1, p2],
        dim=1,
    ).reshape(-1, 4)  # [V * 5, 4]
    a = origin @ planes[:, :3].T + planes[:, 3]  # [R, V * 5] plane value at t = 0
    s = direction @ planes[:, :3].T  # [R, V * 5] its rate along the ray
    ratio = -a / torch.where(s == 0, torch.ones_like(s), s)
    inf = torch.full_like(a, float("inf"))
    lower = torch.where(s > 0, ratio, torch.where((s == 0) & (a < 0), inf, -inf)).amax(dim=1)
    upper = torch.where(s < 0, ratio, torch.where((s == 0) & (a < 0), -inf, inf)).amin(dim=1)
    return lower.clamp(min=near), upper.clamp(max=far)
