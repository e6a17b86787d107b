"""Warp kernels of the tiled rasteriser, part 1b: tile binning and the entries' gradients (float32).

Each (image, Gaussian) pair is projected, boxed (its alpha >= 1/255 extent) and counted in every
tile the box touches (``project_bounds_kernel``); every (pair, tile) intersection is then an
*entry*, put in (image, tile, depth) order with its data gathered contiguously: by a global sort
and ``emit_entries_kernel`` + ``gather_entries_kernel``, or on the CPU by a counting sort in one
pass over the pairs in depth order (``gather_pairs_kernel``, then ``bin_entries_kernel``). After
the raster backward, ``scatter_entry_grads_kernel`` sums the per-entry gradients back into pairs
and Gaussians. Layout: ``warp_kernels``.
"""

from __future__ import annotations

import warp as wp

from physgm.render.settings import ALPHA_MIN, EXTENT_MARGIN_ABS, EXTENT_MARGIN_REL, QMAX_MARGIN
from physgm.render.warp_project_kernels import pair_gaussian, project_pair

_ALPHA_MIN = wp.constant(ALPHA_MIN)
_MARGIN_REL = wp.constant(EXTENT_MARGIN_REL)
_MARGIN_ABS = wp.constant(EXTENT_MARGIN_ABS)
_QMAX_MARGIN = wp.constant(QMAX_MARGIN)


@wp.kernel(enable_backward=False)
def project_bounds_kernel(
    offset: int,  # first pair of this launch (the CPU splits a launch over threads)
    means: wp.array(dtype=wp.vec3),  # [B*N] as in project_kernel
    quats: wp.array(dtype=wp.vec4),  # [B*N]
    scales: wp.array(dtype=wp.vec3),  # [B*N]
    opacities: wp.array(dtype=float),  # [B*N]
    viewmats: wp.array(dtype=wp.mat44),  # [I]
    Ks: wp.array(dtype=wp.mat33),  # [I]
    num_gaussians: int,
    num_cameras: int,
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
    eps2d: float,
    tile_size: int,
    tiles_x: int,
    tiles_per_image: int,
    means2d: wp.array(dtype=wp.vec2),  # [I*N] px, out
    conics: wp.array(dtype=wp.vec3),  # [I*N] out
    depths: wp.array(dtype=float),  # [I*N] camera z (m), 0 when culled, out
    extents: wp.array(dtype=wp.vec2),  # [I*N] half-size (px) of the alpha >= 1/255 box, out
    qmax: wp.array(dtype=float),  # [I*N] largest q with alpha >= 1/255, plus a margin, out
    counts: wp.array(dtype=wp.int32),  # [I*N] tiles touched, out
    spans: wp.array(dtype=wp.vec2i),  # [I*N] global ids of the first and last tile touched, out
    tile_counts: wp.array(dtype=wp.int32),  # [I*tiles] pairs touching each tile, zeroed by the caller
):
    """`project_kernel` and then the pair's box and tiles in one pass. The box mirrors
    `projection.extents_from_cov` and `projection.tile_rects`; the entries of every tile are
    counted with atomics, so the counts are the same in any thread order. A pair touches no tile
    outside its span (row-major ids), so a thread binning a range of tiles can skip the pairs
    whose span misses it."""
    pid = wp.tid() + offset
    img, g = pair_gaussian(pid, num_gaussians, num_cameras)
    m2, con, depth, cd = project_pair(img, g, means, quats, scales, opacities, viewmats, Ks, width, height,
                                      near_plane, far_plane, eps2d)  # fmt: skip
    means2d[pid] = m2
    conics[pid] = con
    depths[pid] = depth
    k2 = 2.0 * wp.log(wp.max(opacities[g] / _ALPHA_MIN, 1.0))
    ext = wp.vec2(0.0, 0.0)
    if cd[0] > 0.0 and k2 > 0.0:
        ext = wp.vec2(
            wp.sqrt(k2 * cd[0]) * (1.0 + _MARGIN_REL) + _MARGIN_ABS,
            wp.sqrt(k2 * cd[1]) * (1.0 + _MARGIN_REL) + _MARGIN_ABS,
        )
    extents[pid] = ext
    qmax[pid] = k2 + _QMAX_MARGIN
    r = tile_rect(m2, ext, width, height, tile_size)
    counts[pid] = wp.max(r[1] - r[0] + 1, 0) * wp.max(r[3] - r[2] + 1, 0)
    first = img * tiles_per_image + r[2] * tiles_x
    spans[pid] = wp.vec2i(first + r[0], first + (r[3] - r[2]) * tiles_x + r[1])
    for ty in range(r[2], r[3] + 1):
        for tx in range(r[0], r[1] + 1):
            wp.atomic_add(tile_counts, img * tiles_per_image + ty * tiles_x + tx, 1)


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


@wp.func
def write_entry(
    e: int,
    pid: int,
    num_gaussians: int,
    num_cameras: int,
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    qmax: wp.array(dtype=float),
    extents: wp.array(dtype=wp.vec2),
    opacities: wp.array(dtype=float),
    colors: wp.array(dtype=wp.vec3),
    e_pair: wp.array(dtype=wp.int64),
    e_gauss: wp.array(dtype=wp.int64),
    e_means2d: wp.array(dtype=wp.vec2),
    e_conics: wp.array(dtype=wp.vec3),
    e_opacities: wp.array(dtype=float),
    e_qmax: wp.array(dtype=float),
    e_colors: wp.array(dtype=wp.vec3),
    e_extents: wp.array(dtype=wp.vec2),
):
    """Entry e is pair pid: copy what the raster kernels read about it."""
    img, g = pair_gaussian(pid, num_gaussians, num_cameras)
    e_pair[e] = wp.int64(pid)
    e_gauss[e] = wp.int64(g)
    e_means2d[e] = means2d[pid]
    e_conics[e] = conics[pid]
    e_opacities[e] = opacities[g]
    e_qmax[e] = qmax[pid]
    e_colors[e] = colors[g]
    e_extents[e] = extents[pid]


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
    write_entry(e, pid, num_gaussians, num_cameras, means2d, conics, qmax, extents, opacities, colors,
                e_pair, e_gauss, e_means2d, e_conics, e_opacities, e_qmax, e_colors, e_extents)  # fmt: skip


@wp.kernel(enable_backward=False)
def gather_pairs_kernel(
    offset: int,  # first row of this launch (the CPU splits a launch over threads)
    order: wp.array(dtype=wp.int64),  # [E] pairs sorted by depth (stable)
    num_gaussians: int,
    num_cameras: int,
    means2d: wp.array(dtype=wp.vec2),  # [I*N] per pair
    conics: wp.array(dtype=wp.vec3),  # [I*N]
    qmax: wp.array(dtype=float),  # [I*N]
    extents: wp.array(dtype=wp.vec2),  # [I*N]
    opacities: wp.array(dtype=float),  # [B*N] per Gaussian
    colors: wp.array(dtype=wp.vec3),  # [B*N]
    spans: wp.array(dtype=wp.vec2i),  # [I*N] per pair (``project_bounds_kernel``)
    d_means2d: wp.array(dtype=wp.vec2),  # [E] row r holds pair order[r], out
    d_conics: wp.array(dtype=wp.vec3),
    d_qmax: wp.array(dtype=float),
    d_extents: wp.array(dtype=wp.vec2),
    d_opacities: wp.array(dtype=float),
    d_colors: wp.array(dtype=wp.vec3),
    d_spans: wp.array(dtype=wp.vec2i),
):
    """What the raster kernels read about each pair, copied in depth order, so that
    ``bin_entries_kernel`` reads it front to back (read through the order, a large image's pairs
    are a cache miss per array each)."""
    r = wp.tid() + offset
    pid = int(order[r])
    img, g = pair_gaussian(pid, num_gaussians, num_cameras)
    d_means2d[r] = means2d[pid]
    d_conics[r] = conics[pid]
    d_qmax[r] = qmax[pid]
    d_extents[r] = extents[pid]
    d_opacities[r] = opacities[g]
    d_colors[r] = colors[g]
    d_spans[r] = spans[pid]


@wp.kernel(enable_backward=False)
def bin_entries_kernel(
    width: int,
    height: int,
    tile_size: int,
    tiles_x: int,
    tiles_per_image: int,
    tile_lo: int,  # this launch appends to global tiles tile_lo .. tile_hi - 1 only (the CPU
    tile_hi: int,  # splits binning over threads by tiles: by images, or within one image)
    cursor: wp.array(dtype=wp.int32),  # [I*tiles] next free entry of each tile; starts at tile_start
    num_gaussians: int,
    num_cameras: int,
    order: wp.array(dtype=wp.int64),  # [E] pairs sorted by depth (stable): the pair of each row
    d_means2d: wp.array(dtype=wp.vec2),  # [E] per row (``gather_pairs_kernel``)
    d_conics: wp.array(dtype=wp.vec3),
    d_qmax: wp.array(dtype=float),
    d_extents: wp.array(dtype=wp.vec2),
    d_opacities: wp.array(dtype=float),
    d_colors: wp.array(dtype=wp.vec3),
    d_spans: wp.array(dtype=wp.vec2i),
    e_pair: wp.array(dtype=wp.int64),  # [M] outputs as in gather_entries_kernel
    e_gauss: wp.array(dtype=wp.int64),
    e_means2d: wp.array(dtype=wp.vec2),
    e_conics: wp.array(dtype=wp.vec3),
    e_opacities: wp.array(dtype=float),
    e_qmax: wp.array(dtype=float),
    e_colors: wp.array(dtype=wp.vec3),
    e_extents: wp.array(dtype=wp.vec2),
):
    """Counting sort: each pair, in depth order, appends itself to every tile it touches.

    Emitting, sorting and gathering in one pass; the order inside a tile is the launch order, so
    this is only correct where a launch runs its threads in sequence (Warp on the CPU). A launch
    walks every row and skips at once the pairs whose span of tiles misses its own.
    """
    row = wp.tid()
    span = d_spans[row]
    if span[1] < tile_lo or span[0] >= tile_hi:
        return
    pid = int(order[row])
    m2 = d_means2d[row]
    ext = d_extents[row]
    r = tile_rect(m2, ext, width, height, tile_size)
    img, g = pair_gaussian(pid, num_gaussians, num_cameras)
    for ty in range(r[2], r[3] + 1):
        for tx in range(r[0], r[1] + 1):
            tile = img * tiles_per_image + ty * tiles_x + tx
            if tile < tile_lo or tile >= tile_hi:
                continue
            e = wp.atomic_add(cursor, tile, 1)  # the old value
            e_pair[e] = wp.int64(pid)
            e_gauss[e] = wp.int64(g)
            e_means2d[e] = m2
            e_conics[e] = d_conics[row]
            e_opacities[e] = d_opacities[row]
            e_qmax[e] = d_qmax[row]
            e_colors[e] = d_colors[row]
            e_extents[e] = ext


@wp.kernel(enable_backward=False)
def scatter_entry_grads_kernel(
    offset: int,  # first entry of this launch (the CPU splits a launch over threads)
    e_pair: wp.array(dtype=wp.int64),  # [M] pair of each sorted entry
    e_gauss: wp.array(dtype=wp.int64),  # [M] Gaussian of each sorted entry
    v_e_means2d: wp.array(dtype=wp.vec2),  # [M] per-entry gradients from the raster backward
    v_e_conics: wp.array(dtype=wp.vec3),
    v_e_opacities: wp.array(dtype=float),
    v_e_colors: wp.array(dtype=wp.vec3),
    v_means2d: wp.array(dtype=wp.vec2),  # [I*N] accumulated per pair, out (zeroed by the caller)
    v_conics: wp.array(dtype=wp.vec3),  # [I*N]
    v_opacities: wp.array(dtype=float),  # [B*N] accumulated per Gaussian, out
    v_colors: wp.array(dtype=wp.vec3),  # [B*N]
):
    """Sums the raster backward's per-entry gradients into pairs and Gaussians (four
    ``index_add_`` in one launch). On the CPU a scene's entries run in order on one thread, so
    the sums are deterministic there."""
    e = wp.tid() + offset
    pid = int(e_pair[e])
    g = int(e_gauss[e])
    wp.atomic_add(v_means2d, pid, v_e_means2d[e])
    wp.atomic_add(v_conics, pid, v_e_conics[e])
    wp.atomic_add(v_opacities, g, v_e_opacities[e])
    wp.atomic_add(v_colors, g, v_e_colors[e])
