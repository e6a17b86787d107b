"""Warp kernels of the tiled rasteriser, part 3: the CPU tile layout, a tile row at a time.

One thread per tile of at most 16 x 16 px, entries in depth order; an entry visits the rows of
its alpha >= 1/255 box, and each row's 16 pixels are one loop that the C++ compiler turns into
SIMD instructions (AVX-512 here: one instruction per row and operation). Every lane of a row is
tested, as in the pixel layout, and lanes drop out by selects, never by branches: a pixel that
is done, off the image, or skips the entry keeps its state bit for bit.

The per-pixel sequence of tests and updates is that of the pixel layout (`warp_raster_kernels`),
except that exp is a vectorisable polynomial (``_EXP``: within 1.0e-7 relative of exp on
[-15, 0], as close as a float32 exp), since a call to expf per lane is not vectorised.

Per-pixel state lives in row buffers ``rows [K, tiles * 16]`` (vec16) and ``row_end [tiles * 16]``,
16 rows per tile, touched only by the tile's thread: forward K = 5 (transmittance, r, g, b, live),
backward K = 9 (running transmittance, colour behind r g b, dL/drgb r g b, dL/dalpha, final
transmittance). Outputs and upstream gradients keep the image layout of the pixel kernels.
"""

from __future__ import annotations

import warp as wp

from physgm.render.settings import ALPHA_MAX, ALPHA_MIN, T_MIN
from physgm.render.warp_raster_kernels import LANES, span, tile_box, vec16, vec16i

# Rows of the forward and backward row buffers.
FWD_ROWS = 5
BWD_ROWS = 9


# The row loops are C++ (``wp.func_native``): in Warp's language the same per-lane code was
# vectorised only in part (Warp unrolls the 16 lanes, and the long unrolled chains exceed what
# the compiler's SLP vectoriser follows), and the backward ran slower than the scalar kernel it
# replaces. A plain C++ loop over the 16 lanes, with selects instead of branches, is vectorised
# whole by the loop vectoriser.
# Constants are pasted in so the snippets use exactly the thresholds of `settings`.
# A row is copied into local arrays and back: through pointers into the row buffers the compiler
# has to allow for overlap, guards the vector loop with run-time checks and takes the scalar path.
_CONSTANTS = f"""
const float alpha_min = {ALPHA_MIN!r}f, alpha_max = {ALPHA_MAX!r}f, t_min = {T_MIN!r}f;
#define ROW_IN(local, buffer, row) __builtin_memcpy(local, wp::address(buffer, row, k), 64)
#define ROW_OUT(local, buffer, row) __builtin_memcpy(wp::address(buffer, row, k), local, 64)
"""

# exp(x) for x <= 0 in arithmetic a vector unit runs: x = k ln2 + r with |r| <= ln2 / 2 (ln2 split
# in two parts, Cody-Waite), exp(r) by its degree-7 Taylor polynomial (remainder < 6e-9 relative),
# 2^k by exact halvings. Inputs below -15 are clamped: such lanes are far below the 1/255 alpha
# threshold (q > 30) and are masked out. Within 1.0e-7 relative of exp on [-15, 0] (measured on
# 320k points; tests/render/test_tile_kernels.py).
_EXP = """
auto exp_lane = [](float x) -> float {
    const float xc = x < -15.0f ? -15.0f : x;
    const float k = __builtin_floorf(xc * 1.44269504088896341f + 0.5f);
    const float r = (xc - k * 0.693359375f) + k * 2.12194440e-4f;
    const float p = 1.0f + r * (1.0f + r * (0.5f + r * (1.0f / 6.0f + r * (1.0f / 24.0f
                    + r * (1.0f / 120.0f + r * (1.0f / 720.0f + r * (1.0f / 5040.0f)))))));
    float n = -k, s = 1.0f;  // n in 0 .. 22; 2^-n by its binary digits
    s = n >= 16.0f ? s * 1.52587890625e-05f : s;  n = n >= 16.0f ? n - 16.0f : n;
    s = n >= 8.0f ? s * 0.00390625f : s;  n = n >= 8.0f ? n - 8.0f : n;
    s = n >= 4.0f ? s * 0.0625f : s;  n = n >= 4.0f ? n - 4.0f : n;
    s = n >= 2.0f ? s * 0.25f : s;  n = n >= 2.0f ? n - 2.0f : n;
    s = n >= 1.0f ? s * 0.5f : s;
    return p * s;
};
"""

_EXP_KERNEL = _EXP + """
float* __restrict out_lanes = reinterpret_cast<float*>(wp::address(out, i));
const float* __restrict x_lanes = reinterpret_cast<const float*>(wp::address(x, i));
#pragma clang loop vectorize(enable) vectorize_width(16) interleave(disable)
for (int j = 0; j < 16; ++j) out_lanes[j] = exp_lane(x_lanes[j]);
"""  # fmt: skip


@wp.func_native(_EXP_KERNEL)
def _exp_row(x: wp.array(dtype=vec16), out: wp.array(dtype=vec16), i: int): ...


@wp.kernel(enable_backward=False)
def exp16_kernel(x: wp.array(dtype=vec16), out: wp.array(dtype=vec16)):
    """The snippets' exp over rows of 16 (tests compare it with exp)."""
    _exp_row(x, out, wp.tid())


# One entry over rows v_first .. v_first + num_rows - 1 of its tile, front to back. Per lane it is
# the pixel layout's step: skip (q > qmax, alpha < 1/255, pixel done), stop (T would drop below
# T_MIN: the pixel is done, nothing added), or composite. Returns the number of pixels that stopped.
_FORWARD_ENTRY = _CONSTANTS + _EXP + """
int stops = 0;
for (int r = 0; r < num_rows; ++r) {
    const int k = row_first + r;
    const float dy = static_cast<float>(v_first + r) + 0.5f - my;
    float trans[16], red[16], green[16], blue[16], on[16];
    int end[16];
    ROW_IN(trans, rows, 0); ROW_IN(red, rows, 1); ROW_IN(green, rows, 2); ROW_IN(blue, rows, 3);
    ROW_IN(on, rows, 4); __builtin_memcpy(end, wp::address(row_end, k), 64);
    #pragma clang loop vectorize(enable) vectorize_width(16) interleave(disable)
    for (int i = 0; i < 16; ++i) {
        const float dx = static_cast<float>(u0 + i) + 0.5f - mx;
        const float q = con[0] * dx * dx + 2.0f * con[1] * dx * dy + con[2] * dy * dy;
        float alpha = opacity * exp_lane(-0.5f * q);
        alpha = alpha_max < alpha ? alpha_max : alpha;
        const bool ok = on[i] > 0.0f && q <= qmax && !(alpha < alpha_min);
        const float next_trans = trans[i] * (1.0f - alpha);
        const bool stop = ok && next_trans < t_min;
        const bool take = ok && !stop;
        const float w = take ? alpha * trans[i] : 0.0f;
        red[i] = red[i] + w * col[0];
        green[i] = green[i] + w * col[1];
        blue[i] = blue[i] + w * col[2];
        trans[i] = take ? next_trans : trans[i];
        end[i] = take ? e + 1 : end[i];
        on[i] = stop ? 0.0f : on[i];
        stops += stop ? 1 : 0;
    }
    ROW_OUT(trans, rows, 0); ROW_OUT(red, rows, 1); ROW_OUT(green, rows, 2); ROW_OUT(blue, rows, 3);
    ROW_OUT(on, rows, 4); __builtin_memcpy(wp::address(row_end, k), end, 64);
}
return stops;
"""  # fmt: skip


@wp.func_native(_FORWARD_ENTRY)
def composite_entry(
    rows: wp.array2d(dtype=vec16), row_end: wp.array(dtype=vec16i), row_first: int, num_rows: int,
    v_first: int, u0: int, mx: float, my: float, con: wp.vec3, qmax: float, opacity: float,
    col: wp.vec3, e: int,
) -> int: ...  # fmt: skip


# One entry over its rows, back to front: per lane the pixel layout's `pair_grads`, masked;
# the entry's gradients are summed per lane, then over the lanes by halving, and stored once.
_BACKWARD_ENTRY = _CONSTANTS + _EXP + """
float s_mx[16], s_my[16], s_c0[16], s_c1[16], s_c2[16], s_o[16], s_r[16], s_g[16], s_b[16];
for (int i = 0; i < 16; ++i) {
    s_mx[i] = s_my[i] = s_c0[i] = s_c1[i] = s_c2[i] = s_o[i] = s_r[i] = s_g[i] = s_b[i] = 0.0f;
}
for (int r = 0; r < num_rows; ++r) {
    const int k = row_first + r;
    const float dy = static_cast<float>(v_first + r) + 0.5f - my;
    float trans_after[16], behind_r[16], behind_g[16], behind_b[16];
    float g_r[16], g_g[16], g_b[16], g_a[16], final_trans[16];
    int end[16];
    ROW_IN(trans_after, rows, 0); ROW_IN(behind_r, rows, 1); ROW_IN(behind_g, rows, 2);
    ROW_IN(behind_b, rows, 3); ROW_IN(g_r, rows, 4); ROW_IN(g_g, rows, 5); ROW_IN(g_b, rows, 6);
    ROW_IN(g_a, rows, 7); ROW_IN(final_trans, rows, 8); __builtin_memcpy(end, wp::address(row_end, k), 64);
    #pragma clang loop vectorize(enable) vectorize_width(16) interleave(disable)
    for (int i = 0; i < 16; ++i) {
        const float dx = static_cast<float>(u0 + i) + 0.5f - mx;
        const float q = con[0] * dx * dx + 2.0f * con[1] * dx * dy + con[2] * dy * dy;
        const float gauss = exp_lane(-0.5f * q);
        const float raw = opacity * gauss;
        const float alpha = alpha_max < raw ? alpha_max : raw;
        const bool ok = e < end[i] && q <= qmax && !(alpha < alpha_min);
        const float a = ok ? alpha : 0.0f;  // a lane that skips the entry keeps its state exactly
        const float inv = 1.0f / (1.0f - a);
        const float trans = trans_after[i] * inv;
        const float w = a * trans;
        const float v_a = g_r[i] * (trans * col[0] - behind_r[i] * inv)
                        + g_g[i] * (trans * col[1] - behind_g[i] * inv)
                        + g_b[i] * (trans * col[2] - behind_b[i] * inv)
                        + g_a[i] * final_trans[i] * inv;
        const bool free = ok && raw < alpha_max;  // the 0.99 clamp has zero gradient
        const float v_q = free ? -0.5f * v_a * raw : 0.0f;
        s_o[i] += free ? v_a * gauss : 0.0f;
        s_c0[i] += v_q * dx * dx;
        s_c1[i] += 2.0f * v_q * dx * dy;
        s_c2[i] += v_q * dy * dy;
        s_mx[i] -= v_q * (2.0f * (con[0] * dx + con[1] * dy));
        s_my[i] -= v_q * (2.0f * (con[1] * dx + con[2] * dy));
        s_r[i] += ok ? w * g_r[i] : 0.0f;
        s_g[i] += ok ? w * g_g[i] : 0.0f;
        s_b[i] += ok ? w * g_b[i] : 0.0f;
        behind_r[i] = behind_r[i] + w * col[0];
        behind_g[i] = behind_g[i] + w * col[1];
        behind_b[i] = behind_b[i] + w * col[2];
        trans_after[i] = trans;
    }
    ROW_OUT(trans_after, rows, 0); ROW_OUT(behind_r, rows, 1); ROW_OUT(behind_g, rows, 2);
    ROW_OUT(behind_b, rows, 3);
}
for (int h = 8; h >= 1; h /= 2) {
    for (int i = 0; i < h; ++i) {
        s_mx[i] += s_mx[i + h]; s_my[i] += s_my[i + h];
        s_c0[i] += s_c0[i + h]; s_c1[i] += s_c1[i + h]; s_c2[i] += s_c2[i + h];
        s_o[i] += s_o[i + h]; s_r[i] += s_r[i + h]; s_g[i] += s_g[i + h]; s_b[i] += s_b[i + h];
    }
}
*wp::address(v_means2d, e) = wp::vec2(s_mx[0], s_my[0]);
*wp::address(v_conics, e) = wp::vec3(s_c0[0], s_c1[0], s_c2[0]);
*wp::address(v_opacities, e) = s_o[0];
*wp::address(v_colors, e) = wp::vec3(s_r[0], s_g[0], s_b[0]);
"""  # fmt: skip


@wp.func_native(_BACKWARD_ENTRY)
def entry_grads(
    rows: wp.array2d(dtype=vec16), row_end: wp.array(dtype=vec16i), row_first: int, num_rows: int,
    v_first: int, u0: int, mx: float, my: float, con: wp.vec3, qmax: float, opacity: float,
    col: wp.vec3, e: int, v_means2d: wp.array(dtype=wp.vec2), v_conics: wp.array(dtype=wp.vec3),
    v_opacities: wp.array(dtype=float), v_colors: wp.array(dtype=wp.vec3),
): ...  # fmt: skip


@wp.kernel(enable_backward=False)
def raster_forward_tile_kernel(
    tile_offset: int,
    tile_size: int,
    tiles_x: int,
    tiles_per_image: int,
    width: int,
    height: int,
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    e_means2d: wp.array(dtype=wp.vec2),
    e_conics: wp.array(dtype=wp.vec3),
    e_opacities: wp.array(dtype=float),
    e_qmax: wp.array(dtype=float),
    e_colors: wp.array(dtype=wp.vec3),
    e_extents: wp.array(dtype=wp.vec2),
    out_rgb: wp.array(dtype=wp.vec3),
    out_trans: wp.array(dtype=float),
    out_end: wp.array(dtype=wp.int32),
    rows: wp.array2d(dtype=vec16),  # [FWD_ROWS, I*tiles*16] scratch
    row_end: wp.array(dtype=vec16i),  # [I*tiles*16] scratch
    tile_work: wp.array(dtype=wp.int32),  # [I*tiles] pixel tests of this tile: the backward's cost
):
    """One thread per tile, entries front to back, each over the rows of its alpha >= 1/255 box."""
    tile = tile_offset + wp.tid()
    img, u0, u1, v0, v1 = tile_box(tile, tile_size, tiles_x, tiles_per_image, width, height)
    row0 = tile * LANES
    start = tile_start[tile]
    num_u = u1 - u0 + 1
    live = vec16()
    for i in range(16):
        live[i] = wp.where(i < num_u, 1.0, 0.0)  # lanes past the image edge never composite
    for r in range(v1 - v0 + 1):
        rows[0, row0 + r] = vec16(1.0)
        rows[1, row0 + r] = vec16(0.0)
        rows[2, row0 + r] = vec16(0.0)
        rows[3, row0 + r] = vec16(0.0)
        rows[4, row0 + r] = live
        row_end[row0 + r] = vec16i(start)
    alive = wp.int32(num_u * (v1 - v0 + 1))
    work = wp.int32(1)  # an empty tile is not free
    for e in range(start, tile_end[tile]):
        if alive == 0:
            break
        m = e_means2d[e]
        ext = e_extents[e]
        su = span(m[0], ext[0], u0, u1)
        sv = span(m[1], ext[1], v0, v1)
        work += wp.max(su[1] - su[0] + 1, 0) * wp.max(sv[1] - sv[0] + 1, 0)
        if su[1] < su[0] or sv[1] < sv[0]:
            continue
        alive -= composite_entry(rows, row_end, row0 + sv[0] - v0, sv[1] - sv[0] + 1, sv[0], u0,
                                 m[0], m[1], e_conics[e], e_qmax[e], e_opacities[e], e_colors[e],
                                 e)  # fmt: skip
    base = img * height * width
    for r in range(v1 - v0 + 1):
        trans = rows[0, row0 + r]
        red = rows[1, row0 + r]
        green = rows[2, row0 + r]
        blue = rows[3, row0 + r]
        end = row_end[row0 + r]
        for i in range(num_u):
            pix = base + (v0 + r) * width + u0 + i
            out_rgb[pix] = wp.vec3(red[i], green[i], blue[i])
            out_trans[pix] = trans[i]
            out_end[pix] = end[i]
    tile_work[tile] = work


@wp.kernel(enable_backward=False)
def raster_backward_tile_kernel(
    tile_offset: int,
    tile_size: int,
    tiles_x: int,
    tiles_per_image: int,
    width: int,
    height: int,
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    e_means2d: wp.array(dtype=wp.vec2),
    e_conics: wp.array(dtype=wp.vec3),
    e_opacities: wp.array(dtype=float),
    e_qmax: wp.array(dtype=float),
    e_colors: wp.array(dtype=wp.vec3),
    e_extents: wp.array(dtype=wp.vec2),
    out_trans: wp.array(dtype=float),
    out_end: wp.array(dtype=wp.int32),
    v_rgb: wp.array(dtype=wp.vec3),
    v_alpha: wp.array(dtype=float),
    rows: wp.array2d(dtype=vec16),  # [BWD_ROWS, I*tiles*16] scratch
    row_end: wp.array(dtype=vec16i),  # [I*tiles*16] scratch
    v_means2d: wp.array(dtype=wp.vec2),
    v_conics: wp.array(dtype=wp.vec3),
    v_opacities: wp.array(dtype=float),
    v_colors: wp.array(dtype=wp.vec3),
):
    """One thread per tile, entries back to front (transmittance recovered by division); each
    entry's gradient is summed over lanes and rows and stored once."""
    tile = tile_offset + wp.tid()
    img, u0, u1, v0, v1 = tile_box(tile, tile_size, tiles_x, tiles_per_image, width, height)
    row0 = tile * LANES
    base = img * height * width
    start = tile_start[tile]
    num_u = u1 - u0 + 1
    last = start  # entries at or after every pixel's end were never composited
    for r in range(v1 - v0 + 1):
        final = vec16()
        g_red = vec16()
        g_green = vec16()
        g_blue = vec16()
        g_alpha = vec16()
        end = vec16i(start)  # lanes past the image edge: no entry is before their end
        for i in range(num_u):
            pix = base + (v0 + r) * width + u0 + i
            g = v_rgb[pix]
            final[i] = out_trans[pix]
            g_red[i] = g[0]
            g_green[i] = g[1]
            g_blue[i] = g[2]
            g_alpha[i] = v_alpha[pix]
            end[i] = out_end[pix]
            last = wp.max(last, end[i])
        rows[0, row0 + r] = final
        rows[1, row0 + r] = vec16(0.0)
        rows[2, row0 + r] = vec16(0.0)
        rows[3, row0 + r] = vec16(0.0)
        rows[4, row0 + r] = g_red
        rows[5, row0 + r] = g_green
        rows[6, row0 + r] = g_blue
        rows[7, row0 + r] = g_alpha
        rows[8, row0 + r] = final
        row_end[row0 + r] = end
    for kk in range(last - start):
        e = last - 1 - kk
        m = e_means2d[e]
        ext = e_extents[e]
        su = span(m[0], ext[0], u0, u1)
        sv = span(m[1], ext[1], v0, v1)
        if su[1] < su[0] or sv[1] < sv[0]:
            continue
        entry_grads(rows, row_end, row0 + sv[0] - v0, sv[1] - sv[0] + 1, sv[0], u0, m[0], m[1],
                    e_conics[e], e_qmax[e], e_opacities[e], e_colors[e], e,
                    v_means2d, v_conics, v_opacities, v_colors)  # fmt: skip
