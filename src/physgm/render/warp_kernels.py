"""Warp kernels of the tiled rasteriser, part 1: projection and tile binning (float32).

Layout: images I = B * C are flattened; an (image, Gaussian) pair has index
pid = img * N + n and reads Gaussian g = (img // C) * N + n. After binning, every
(pair, tile) intersection is an *entry*; entries are sorted by (image, tile, depth) and their
data gathered into contiguous arrays, so a tile's Gaussians are entries
tile_start[t] .. tile_end[t] - 1. The math mirrors `projection.py`; the raster kernels are in
`warp_raster_kernels.py`.
"""

from __future__ import annotations

import warp as wp

from physgm.render.settings import (
    ALPHA_MIN,
    EXTENT_MARGIN_ABS,
    EXTENT_MARGIN_REL,
    FOV_CLAMP,
    QMAX_MARGIN,
)

_ALPHA_MIN = wp.constant(ALPHA_MIN)
_FOV_CLAMP = wp.constant(FOV_CLAMP)
_MARGIN_REL = wp.constant(EXTENT_MARGIN_REL)
_MARGIN_ABS = wp.constant(EXTENT_MARGIN_ABS)
_QMAX_MARGIN = wp.constant(QMAX_MARGIN)


@wp.func
def quat_to_rotmat(q: wp.vec4) -> wp.mat33:
    """Rotation matrix of a unit quaternion stored (w, x, y, z)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )  # fmt: skip


@wp.kernel
def project_kernel(
    means: wp.array(dtype=wp.vec3),  # [B*N] world (m)
    quats: wp.array(dtype=wp.vec4),  # [B*N] (w, x, y, z), any non-zero norm
    scales: wp.array(dtype=wp.vec3),  # [B*N] linear std (m)
    opacities: wp.array(dtype=float),  # [B*N]
    viewmats: wp.array(dtype=wp.mat44),  # [I] world-to-camera
    Ks: wp.array(dtype=wp.mat33),  # [I]
    num_gaussians: int,
    num_cameras: int,
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
    eps2d: float,
    means2d: wp.array(dtype=wp.vec2),  # [I*N] px, out
    conics: wp.array(dtype=wp.vec3),  # [I*N] inverse 2D covariance (a, b, c), out
    depths: wp.array(dtype=float),  # [I*N] camera z (m), 0 when culled, out
    cov_diag: wp.array(dtype=wp.vec2),  # [I*N] diagonal of the 2D covariance, 0 when culled, out
):
    """EWA projection of one (image, Gaussian) pair; differentiated by Warp's adjoint."""
    pid = wp.tid()
    img = pid // num_gaussians
    g = (img // num_cameras) * num_gaussians + (pid - img * num_gaussians)
    view = viewmats[img]
    rot_w = wp.mat33(
        view[0, 0], view[0, 1], view[0, 2],
        view[1, 0], view[1, 1], view[1, 2],
        view[2, 0], view[2, 1], view[2, 2],
    )  # fmt: skip
    p = rot_w * means[g] + wp.vec3(view[0, 3], view[1, 3], view[2, 3])
    z = p[2]
    m2 = wp.vec2(0.0, 0.0)
    con = wp.vec3(0.0, 0.0, 0.0)
    depth = wp.float32(0.0)
    cd = wp.vec2(0.0, 0.0)
    if z >= near_plane and z <= far_plane and opacities[g] >= _ALPHA_MIN:
        K = Ks[img]
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        lim_x = _FOV_CLAMP * 0.5 * float(width) / fx
        lim_y = _FOV_CLAMP * 0.5 * float(height) / fy
        tx = z * wp.min(wp.max(p[0] / z, -cx / fx - lim_x), (float(width) - cx) / fx + lim_x)
        ty = z * wp.min(wp.max(p[1] / z, -cy / fy - lim_y), (float(height) - cy) / fy + lim_y)
        j0 = wp.vec3(fx / z, 0.0, -fx * tx / (z * z))
        j1 = wp.vec3(0.0, fy / z, -fy * ty / (z * z))
        rot_t = wp.transpose(rot_w * quat_to_rotmat(wp.normalize(quats[g])))
        s = scales[g]
        a0 = wp.cw_mul(rot_t * j0, s)  # rows of A = J W R S
        a1 = wp.cw_mul(rot_t * j1, s)
        cov_a0 = wp.dot(a0, a0)
        cov_b = wp.dot(a0, a1)
        cov_c0 = wp.dot(a1, a1)
        m01 = a0[0] * a1[1] - a0[1] * a1[0]
        m02 = a0[0] * a1[2] - a0[2] * a1[0]
        m12 = a0[1] * a1[2] - a0[2] * a1[1]
        det = m01 * m01 + m02 * m02 + m12 * m12 + eps2d * (cov_a0 + cov_c0) + eps2d * eps2d
        if det > 0.0:
            cov_a = cov_a0 + eps2d
            cov_c = cov_c0 + eps2d
            con = wp.vec3(cov_c / det, -cov_b / det, cov_a / det)
            m2 = wp.vec2(fx * p[0] / z + cx, fy * p[1] / z + cy)
            depth = z
            cd = wp.vec2(cov_a, cov_c)
    means2d[pid] = m2
    conics[pid] = con
    depths[pid] = depth
    cov_diag[pid] = cd


@wp.kernel(enable_backward=False)
def pair_bounds_kernel(
    means2d: wp.array(dtype=wp.vec2),  # [I*N]
    cov_diag: wp.array(dtype=wp.vec2),  # [I*N] 0 when culled
    opacities: wp.array(dtype=float),  # [B*N]
    num_gaussians: int,
    num_cameras: int,
    width: int,
    height: int,
    tile_size: int,
    extents: wp.array(dtype=wp.vec2),  # [I*N] half-size (px) of the alpha >= 1/255 box, out
    qmax: wp.array(dtype=float),  # [I*N] largest q with alpha >= 1/255, plus a margin, out
    counts: wp.array(dtype=wp.int32),  # [I*N] tiles touched, out
):
    """Mirrors `projection.extents_from_cov` and `projection.tile_rects`."""
    pid = wp.tid()
    img = pid // num_gaussians
    g = (img // num_cameras) * num_gaussians + (pid - img * num_gaussians)
    cd = cov_diag[pid]
    k2 = 2.0 * wp.log(wp.max(opacities[g] / _ALPHA_MIN, 1.0))
    ext = wp.vec2(0.0, 0.0)
    if cd[0] > 0.0 and k2 > 0.0:
        ext = wp.vec2(
            wp.sqrt(k2 * cd[0]) * (1.0 + _MARGIN_REL) + _MARGIN_ABS,
            wp.sqrt(k2 * cd[1]) * (1.0 + _MARGIN_REL) + _MARGIN_ABS,
        )
    extents[pid] = ext
    qmax[pid] = k2 + _QMAX_MARGIN
    r = tile_rect(means2d[pid], ext, width, height, tile_size)
    counts[pid] = wp.max(r[1] - r[0] + 1, 0) * wp.max(r[3] - r[2] + 1, 0)


@wp.func
def tile_rect(m: wp.vec2, ext: wp.vec2, width: int, height: int, tile_size: int) -> wp.vec4i:
    """Inclusive tile range (x0, x1, y0, y1) of the box m +- ext; x1 < x0 when empty."""
    empty = wp.vec4i(0, -1, 0, -1)
    if ext[0] <= 0.0:
        return empty
    lo_x = wp.ceil(m[0] - ext[0] - 0.5)
    hi_x = wp.floor(m[0] + ext[0] - 0.5)
    lo_y = wp.ceil(m[1] - ext[1] - 0.5)
    hi_y = wp.floor(m[1] + ext[1] - 0.5)
    w1 = float(width - 1)
    h1 = float(height - 1)
    if lo_x > hi_x or hi_x < 0.0 or lo_x > w1 or lo_y > hi_y or hi_y < 0.0 or lo_y > h1:
        return empty
    # clip in float before the int cast: off-screen means can be huge
    x0 = int(wp.clamp(lo_x, 0.0, w1)) // tile_size
    x1 = int(wp.clamp(hi_x, 0.0, w1)) // tile_size
    y0 = int(wp.clamp(lo_y, 0.0, h1)) // tile_size
    y1 = int(wp.clamp(hi_y, 0.0, h1)) // tile_size
    return wp.vec4i(x0, x1, y0, y1)


@wp.kernel(enable_backward=False)
def emit_entries_kernel(
    means2d: wp.array(dtype=wp.vec2),  # [I*N]
    extents: wp.array(dtype=wp.vec2),  # [I*N]
    offsets: wp.array(dtype=wp.int32),  # [I*N] exclusive prefix sum of counts
    num_gaussians: int,
    width: int,
    height: int,
    tile_size: int,
    tiles_x: int,
    tiles_per_image: int,
    entry_tile: wp.array(dtype=wp.int32),  # [M] global tile id img * tiles_per_image + t, out
    entry_pair: wp.array(dtype=wp.int32),  # [M] pair index, out
):
    pid = wp.tid()
    img = pid // num_gaussians
    r = tile_rect(means2d[pid], extents[pid], width, height, tile_size)
    k = offsets[pid]
    for ty in range(r[2], r[3] + 1):
        for tx in range(r[0], r[1] + 1):
            entry_tile[k] = img * tiles_per_image + ty * tiles_x + tx
            entry_pair[k] = pid
            k += 1


@wp.kernel(enable_backward=False)
def gather_entries_kernel(
    order: wp.array(dtype=wp.int64),  # [M] sorting permutation of the emitted entries
    entry_pair: wp.array(dtype=wp.int32),  # [M] pair of each emitted (unsorted) entry
    num_gaussians: int,
    num_cameras: int,
    means2d: wp.array(dtype=wp.vec2),  # [I*N] per pair
    conics: wp.array(dtype=wp.vec3),  # [I*N]
    qmax: wp.array(dtype=float),  # [I*N]
    extents: wp.array(dtype=wp.vec2),  # [I*N]
    opacities: wp.array(dtype=float),  # [B*N] per Gaussian
    colors: wp.array(dtype=wp.vec3),  # [B*N]
    e_pair: wp.array(dtype=wp.int64),  # [M] sorted entries' pair, out
    e_gauss: wp.array(dtype=wp.int64),  # [M] sorted entries' Gaussian, out
    e_means2d: wp.array(dtype=wp.vec2),  # [M] out, and so on
    e_conics: wp.array(dtype=wp.vec3),
    e_opacities: wp.array(dtype=float),
    e_qmax: wp.array(dtype=float),
    e_colors: wp.array(dtype=wp.vec3),
    e_extents: wp.array(dtype=wp.vec2),
):
    """Copies what the raster kernels read into arrays laid out in (image, tile, depth) order."""
    e = wp.tid()
    pid = entry_pair[int(order[e])]
    img = pid // num_gaussians
    g = (img // num_cameras) * num_gaussians + (pid - img * num_gaussians)
    e_pair[e] = wp.int64(pid)
    e_gauss[e] = wp.int64(g)
    e_means2d[e] = means2d[pid]
    e_conics[e] = conics[pid]
    e_opacities[e] = opacities[g]
    e_qmax[e] = qmax[pid]
    e_colors[e] = colors[g]
    e_extents[e] = extents[pid]
