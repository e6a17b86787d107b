"""Warp kernels of the tiled rasteriser, part 2: forward and backward compositing, pixel layout.

The rasteriser has two layouts with the same per-pixel steps and identical argument lists (see
`warp_backend.py`):

* pixel layout (here), one thread per pixel looping over its tile's depth-sorted entries. Good
  for CUDA; gradients go to per-entry slots with `atomic_add`.
* tile layout (`warp_tile_kernels`), one thread per tile looping over entries and, for each,
  over the rows of the entry's alpha >= 1/255 box, 16 pixels per SIMD row. Good for CPU; each
  entry's gradient is summed in registers and stored once, without atomics.

Entry e of tile t lies in tile_start[t] .. tile_end[t] - 1, sorted front to back.
"""

from __future__ import annotations

import warp as wp

from physgm.render.settings import ALPHA_MAX, ALPHA_MIN, T_MIN

_ALPHA_MIN = wp.constant(ALPHA_MIN)
_ALPHA_MAX = wp.constant(ALPHA_MAX)
_T_MIN = wp.constant(T_MIN)
# A row of pixels of the tile layout; declared here because both layouts take the row buffers.
LANES = 16
vec16 = wp.types.vector(length=LANES, dtype=wp.float32)
vec16i = wp.types.vector(length=LANES, dtype=wp.int32)


@wp.func
def conic_form(con: wp.vec3, dx: float, dy: float) -> float:
    """q = d^T Sigma2d^-1 d for the offset d = pixel centre - mean."""
    return con[0] * dx * dx + 2.0 * con[1] * dx * dy + con[2] * dy * dy


@wp.func
def pixel_of(tid: int, tile_offset: int, tile_size: int, tiles_x: int, tiles_per_image: int):
    """(tile, image, u, v) of thread tid in a pixel-layout launch starting at `tile_offset`."""
    per_tile = tile_size * tile_size
    tile = tile_offset + tid // per_tile
    local = tid - (tid // per_tile) * per_tile
    img = tile // tiles_per_image
    t = tile - img * tiles_per_image
    ty = t // tiles_x
    u = (t - ty * tiles_x) * tile_size + local - (local // tile_size) * tile_size
    v = ty * tile_size + local // tile_size
    return tile, img, u, v


@wp.func
def tile_box(tile: int, tile_size: int, tiles_x: int, tiles_per_image: int, width: int, height: int):
    """(image, u0, u1, v0, v1): inclusive pixel range of a tile, clipped to the image."""
    img = tile // tiles_per_image
    t = tile - img * tiles_per_image
    ty = t // tiles_x
    u0 = (t - ty * tiles_x) * tile_size
    v0 = ty * tile_size
    return img, u0, wp.min(u0 + tile_size, width) - 1, v0, wp.min(v0 + tile_size, height) - 1


@wp.func
def span(centre: float, extent: float, lo: int, hi: int) -> wp.vec2i:
    """Inclusive pixel indices whose centres lie in centre +- extent, clipped to [lo, hi]."""
    a = wp.clamp(wp.ceil(centre - extent - 0.5), float(lo), float(hi + 1))
    b = wp.clamp(wp.floor(centre + extent - 0.5), float(lo - 1), float(hi))
    return wp.vec2i(int(a), int(b))


@wp.kernel(enable_backward=False)
def raster_forward_pixel_kernel(
    tile_offset: int,
    tile_size: int,
    tiles_x: int,
    tiles_per_image: int,
    width: int,
    height: int,
    tile_start: wp.array(dtype=wp.int32),  # [I*tiles] first entry of each tile
    tile_end: wp.array(dtype=wp.int32),  # [I*tiles] one past its last entry
    e_means2d: wp.array(dtype=wp.vec2),  # [M] gathered per entry (px)
    e_conics: wp.array(dtype=wp.vec3),  # [M]
    e_opacities: wp.array(dtype=float),  # [M]
    e_qmax: wp.array(dtype=float),  # [M] q above which alpha < 1/255 for sure
    e_colors: wp.array(dtype=wp.vec3),  # [M]
    e_extents: wp.array(dtype=wp.vec2),  # [M] half-size of the alpha >= 1/255 box (tile layout)
    out_rgb: wp.array(dtype=wp.vec3),  # [I*H*W] colour without background, out
    out_trans: wp.array(dtype=float),  # [I*H*W] final transmittance, out
    out_end: wp.array(dtype=wp.int32),  # [I*H*W] one past the last entry composited, out
    rows: wp.array2d(dtype=vec16),  # scratch of the tile layout (warp_tile_kernels), unused here
    row_end: wp.array(dtype=vec16i),  # scratch of the tile layout, unused here
    tile_work: wp.array(dtype=wp.int32),  # [I*tiles] pixel tests per tile, out (tile layout only)
):
    """One thread per pixel, front to back; stops before T would drop below T_MIN."""
    tile, img, u, v = pixel_of(wp.tid(), tile_offset, tile_size, tiles_x, tiles_per_image)
    if u >= width or v >= height:
        return
    pix = (img * height + v) * width + u
    px = float(u) + 0.5
    py = float(v) + 0.5
    start = tile_start[tile]
    trans = wp.float32(1.0)
    rgb = wp.vec3(0.0, 0.0, 0.0)
    end = start
    for e in range(start, tile_end[tile]):
        m = e_means2d[e]
        q = conic_form(e_conics[e], px - m[0], py - m[1])
        if q > e_qmax[e]:
            continue  # cheap rejection before exp; the exact test follows
        alpha = wp.min(_ALPHA_MAX, e_opacities[e] * wp.exp(-0.5 * q))
        if alpha < _ALPHA_MIN:
            continue
        next_trans = trans * (1.0 - alpha)
        if next_trans < _T_MIN:
            break
        rgb += (alpha * trans) * e_colors[e]
        trans = next_trans
        end = e + 1
    out_rgb[pix] = rgb
    out_trans[pix] = trans
    out_end[pix] = end


@wp.func
def pair_grads(
    g_rgb: wp.vec3, g_alpha: float, trans_final: float, trans_after: float, behind: wp.vec3,
    alpha: float, raw: float, gauss: float, col: wp.vec3, con: wp.vec3, dx: float, dy: float,
):  # fmt: skip
    """Gradients of one composited (pixel, entry) pair, walking back to front.

    Returns (transmittance in front of the entry, colour composited from it and behind,
    d/d colour, d/d opacity, d/d conic, d/d mean2d).
    """
    inv = 1.0 / (1.0 - alpha)  # one division; vec3 / scalar would be three
    trans = trans_after * inv
    v_col = (alpha * trans) * g_rgb
    v_a = wp.dot(g_rgb, trans * col - behind * inv) + g_alpha * trans_final * inv
    v_o = wp.float32(0.0)
    v_con = wp.vec3(0.0, 0.0, 0.0)
    v_m = wp.vec2(0.0, 0.0)
    if raw < _ALPHA_MAX:  # the 0.99 clamp has zero gradient
        v_o = v_a * gauss
        v_q = -0.5 * v_a * raw
        v_con = wp.vec3(v_q * dx * dx, 2.0 * v_q * dx * dy, v_q * dy * dy)
        v_m = -v_q * wp.vec2(2.0 * (con[0] * dx + con[1] * dy), 2.0 * (con[1] * dx + con[2] * dy))
    return trans, behind + (alpha * trans) * col, v_col, v_o, v_con, v_m


@wp.kernel(enable_backward=False)
def raster_backward_pixel_kernel(
    tile_offset: int,
    tile_size: int,
    tiles_x: int,
    tiles_per_image: int,
    width: int,
    height: int,
    tile_start: wp.array(dtype=wp.int32),  # [I*tiles]
    tile_end: wp.array(dtype=wp.int32),  # [I*tiles]
    e_means2d: wp.array(dtype=wp.vec2),  # [M]
    e_conics: wp.array(dtype=wp.vec3),  # [M]
    e_opacities: wp.array(dtype=float),  # [M]
    e_qmax: wp.array(dtype=float),  # [M]
    e_colors: wp.array(dtype=wp.vec3),  # [M]
    e_extents: wp.array(dtype=wp.vec2),  # [M]
    out_trans: wp.array(dtype=float),  # [I*H*W] from the forward
    out_end: wp.array(dtype=wp.int32),  # [I*H*W] from the forward
    v_rgb: wp.array(dtype=wp.vec3),  # [I*H*W] dL/d rgb (foreground part)
    v_alpha: wp.array(dtype=float),  # [I*H*W] dL/d alpha
    rows: wp.array2d(dtype=vec16),  # scratch of the tile layout (warp_tile_kernels), unused here
    row_end: wp.array(dtype=vec16i),  # scratch of the tile layout, unused here
    v_means2d: wp.array(dtype=wp.vec2),  # [M] per-entry gradients, zero-initialised
    v_conics: wp.array(dtype=wp.vec3),  # [M]
    v_opacities: wp.array(dtype=float),  # [M]
    v_colors: wp.array(dtype=wp.vec3),  # [M]
):
    """One thread per pixel, back to front, transmittance recovered by division.

    An entry belongs to one tile, so its slot is shared only by that tile's pixels: atomic on
    CUDA. On CPU Warp runs a launch serially, `atomic_add` compiles to a plain add, and the
    Python threads get disjoint tile ranges, so there is never a concurrent writer.
    """
    tile, img, u, v = pixel_of(wp.tid(), tile_offset, tile_size, tiles_x, tiles_per_image)
    if u >= width or v >= height:
        return
    pix = (img * height + v) * width + u
    px = float(u) + 0.5
    py = float(v) + 0.5
    start = tile_start[tile]
    end = out_end[pix]
    trans_final = out_trans[pix]
    trans = trans_final
    g_rgb = v_rgb[pix]
    g_alpha = v_alpha[pix]
    behind = wp.vec3(0.0, 0.0, 0.0)  # colour composited behind the current entry
    for k in range(end - start):
        e = end - 1 - k
        m = e_means2d[e]
        dx = px - m[0]
        dy = py - m[1]
        con = e_conics[e]
        q = conic_form(con, dx, dy)
        if q > e_qmax[e]:
            continue
        gauss = wp.exp(-0.5 * q)
        raw = e_opacities[e] * gauss
        alpha = wp.min(_ALPHA_MAX, raw)
        if alpha < _ALPHA_MIN:
            continue
        trans, behind, v_col, v_o, v_con, v_m = pair_grads(
            g_rgb, g_alpha, trans_final, trans, behind, alpha, raw, gauss, e_colors[e], con, dx, dy
        )
        wp.atomic_add(v_colors, e, v_col)
        wp.atomic_add(v_opacities, e, v_o)
        wp.atomic_add(v_conics, e, v_con)
        wp.atomic_add(v_means2d, e, v_m)
