"""CPU ray casting of triangle meshes in numpy (primary rays only), for the mesh importer.

``cast_rays`` bins triangles to 16 x 16 pixel tiles by their projected bounding boxes and runs
a vectorised Moller-Trumbore test of each tile's rays against that tile's triangles only.
``cast_rays_brute`` tests every ray against every triangle: the slow twin used in tests.
Both return, per pixel, the nearest hit's triangle index (-1 for a miss), distance and
barycentric coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_EPS = 1e-12


@dataclass
class Hits:
    """Nearest hits of an H x W image of rays."""

    face: np.ndarray  # [H, W] int64 triangle index, -1 = miss
    t: np.ndarray  # [H, W] distance along the (unit) ray, m; inf = miss
    bary: np.ndarray  # [H, W, 3] barycentric coordinates of the hit (w0, w1, w2)


def camera_rays(c2w: np.ndarray, K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Origin [3] and unit directions [H, W, 3] through pixel centres (OpenCV camera)."""
    v, u = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d = cam @ c2w[:3, :3].T
    return c2w[:3, 3].copy(), d / np.linalg.norm(d, axis=-1, keepdims=True)


def _intersect(
    origin: np.ndarray, dirs: np.ndarray, tri: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit of rays [R, 3] from one origin against triangles [M, 3, 3] (two-sided).

    Returns (index into tri or -1 [R], t [R], u [R], v [R]).
    """
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]  # [M, 3]
    s = origin - tri[:, 0]  # [M, 3]
    q = np.cross(s, e1)  # [M, 3], independent of the ray since the origin is shared
    p = np.cross(dirs[:, None, :], e2[None])  # [R, M, 3]
    det = np.einsum("rmk,mk->rm", p, e1)
    ok = np.abs(det) > _EPS
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    u = np.einsum("rmk,mk->rm", p, s) * inv
    v = (dirs @ q.T) * inv
    t = np.einsum("mk,mk->m", e2, q)[None] * inv  # [R, M]
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
    t = np.where(hit, t, np.inf)
    best = t.argmin(1)
    rows = np.arange(len(dirs))
    tb = t[rows, best]
    found = np.isfinite(tb)
    return (
        np.where(found, best, -1),
        tb,
        np.where(found, u[rows, best], 0.0),
        np.where(found, v[rows, best], 0.0),
    )


def _nearest(origin: np.ndarray, dirs: np.ndarray, triangles: np.ndarray, idx: np.ndarray, chunk: int = 2048):
    """``_intersect`` over triangles[idx] in chunks (bounded memory); returns indices into idx."""
    best = None
    for c0 in range(0, len(idx), chunk):
        f, t, u, v = _intersect(origin, dirs, triangles[idx[c0 : c0 + chunk]])
        f = np.where(f >= 0, f + c0, -1)
        if best is None:
            best = [f, t, u, v]
            continue
        closer = t < best[1]
        best = [np.where(closer, a, b) for a, b in zip((f, t, u, v), best, strict=True)]
    return best


def _pack(face, t, u, v, shape) -> Hits:
    bary = np.stack([1 - u - v, u, v], -1)
    return Hits(face.reshape(shape), t.reshape(shape), bary.reshape(*shape, 3))


def cast_rays_brute(triangles: np.ndarray, c2w: np.ndarray, K: np.ndarray, width: int, height: int) -> Hits:
    """Every ray against every triangle [M, 3, 3]: slow reference for tests."""
    origin, dirs = camera_rays(c2w, K, width, height)
    face, t, u, v = _intersect(origin, dirs.reshape(-1, 3), triangles)
    return _pack(face, t, u, v, (height, width))


def cast_rays(
    triangles: np.ndarray, c2w: np.ndarray, K: np.ndarray, width: int, height: int, tile: int = 16
) -> Hits:
    """Nearest hits for an image, binning triangles [M, 3, 3] (world, m) to screen tiles.

    Triangles must lie in front of the camera (true for objects inside the camera orbit);
    those crossing the camera plane are tested in every tile, so the result stays exact.
    """
    origin, dirs = camera_rays(c2w, K, width, height)
    w2c = np.linalg.inv(c2w)
    cam = triangles @ w2c[:3, :3].T + w2c[:3, 3]  # [M, 3, 3] camera coordinates
    z = cam[..., 2]
    front = (z > 1e-6).all(1)
    px = np.where(front[:, None], K[0, 0] * cam[..., 0] / np.where(front[:, None], z, 1) + K[0, 2], 0)
    py = np.where(front[:, None], K[1, 1] * cam[..., 1] / np.where(front[:, None], z, 1) + K[1, 2], 0)
    # Pixel centres are at +0.5: a tile [x0, x1) holds centres in [x0 + 0.5, x1 - 0.5].
    lo_x, hi_x = np.where(front, px.min(1), -np.inf), np.where(front, px.max(1), np.inf)
    lo_y, hi_y = np.where(front, py.min(1), -np.inf), np.where(front, py.max(1), np.inf)
    face = np.full((height, width), -1, dtype=np.int64)
    t = np.full((height, width), np.inf)
    u = np.zeros((height, width))
    v = np.zeros((height, width))
    for y0 in range(0, height, tile):
        y1 = min(y0 + tile, height)
        rows = (hi_y >= y0 + 0.5 - 1e-6) & (lo_y <= y1 - 0.5 + 1e-6)
        for x0 in range(0, width, tile):
            x1 = min(x0 + tile, width)
            idx = np.flatnonzero(rows & (hi_x >= x0 + 0.5 - 1e-6) & (lo_x <= x1 - 0.5 + 1e-6))
            if idx.size == 0:
                continue
            f, tt, uu, vv = _nearest(origin, dirs[y0:y1, x0:x1].reshape(-1, 3), triangles, idx)
            shape = (y1 - y0, x1 - x0)
            face[y0:y1, x0:x1] = np.where(f >= 0, idx[np.maximum(f, 0)], -1).reshape(shape)
            t[y0:y1, x0:x1], u[y0:y1, x0:x1], v[y0:y1, x0:x1] = (
                tt.reshape(shape),
                uu.reshape(shape),
                vv.reshape(shape),
            )
    return Hits(face, t, np.stack([1 - u - v, u, v], -1))
