"""Tiled Warp rasteriser with an explicit backward pass, wrapped as a torch autograd Function.

Pipeline (kernels in `warp_project_kernels.py` and `warp_bin_kernels.py`, both reached through
`warp_kernels`, then `warp_raster_kernels.py` and `warp_tile_kernels.py`; torch ops in between):
project, box and tiles per pair (I*N pairs, one kernel), entries per tile -> prefix sum -> entries
in (image, tile, depth) order with their data gathered contiguously -> raster forward. The ordering
step is a counting sort on the CPU (pairs sorted by depth append themselves to their tiles in
serial launches, one per group of images or range of tiles) and a global key sort on CUDA
(``RasterSettings.warp_binning``).
Backward: raster backward into per-entry slots -> summed into pairs / Gaussians -> the
projection's hand-written vector-Jacobian product (tested against Warp's generated adjoint).
The same code runs on CPU and CUDA (tile layout with 16-pixel SIMD rows on CPU, pixel layout on
CUDA). On the CPU the launches are split over Python threads (``physgm.parallel``), which run in
parallel because a Warp launch releases the GIL: the raster launches by tiles, the projection by
pairs (each thread counting tiles into its own row), the binning by images or, within one image,
by the raster's tile ranges, and the backward's per-entry launches by scenes (``_cuts``), so no
two threads write the same memory.
"""

from __future__ import annotations

import bisect
import itertools

import torch
import warp as wp
from torch import Tensor

from physgm.parallel import run_launches
from physgm.render import warp_kernels as K
from physgm.render import warp_raster_kernels as R
from physgm.render import warp_tile_kernels as T
from physgm.render.batch import SplatBatch
from physgm.render.projection import radii_px
from physgm.render.settings import RasterSettings, single_threaded_torch
from physgm.warp_runtime import ensure_loaded


def _arr(t: Tensor, dtype) -> ArrayView:
    """Zero-copy Warp kernel argument for a contiguous torch tensor (no Warp gradients).

    Returns the array descriptor a launch packs (data pointer, shape, byte strides) rather than a
    ``wp.array``, which ``wp.launch`` would check against the kernel signature and then turn into
    this descriptor on every call. The descriptor holds the tensor, so the memory lives as long
    as the argument. Raises ValueError unless the tensor holds ``dtype`` elements (float32,
    int32 or int64 scalars, trailing dimensions = its shape).
    """
    t = t.contiguous()
    inner = 2 if wp.types.type_is_matrix(dtype) else 1 if wp.types.type_is_vector(dtype) else 0
    shape = tuple(t.shape[: t.dim() - inner])
    scalar = getattr(dtype, "_wp_scalar_type_", dtype)
    element_shape = tuple(t.shape[t.dim() - inner :]) if t.dim() >= inner else None
    if t.dtype != _TORCH_SCALARS[scalar] or element_shape != tuple(getattr(dtype, "_shape_", ())):
        raise ValueError(
            f"a {t.dtype} tensor of shape {tuple(t.shape)} does not hold {dtype.__name__} elements"
        )
    stride, strides = wp.types.type_size_in_bytes(dtype), []
    for n in reversed(shape):
        strides.append(stride)
        stride *= n
    view = ArrayView(data=t.data_ptr(), grad=0, ndim=len(shape), shape=shape, strides=strides[::-1])
    view.tensor = t  # keeps the memory alive as long as the view
    return view


# The C struct of a Warp array argument; private in Warp, so warp-lang is pinned (pyproject.toml)
# and every parity test launches through it.
ArrayView = wp._src.types.array_t
_TORCH_SCALARS = {wp.float32: torch.float32, wp.int32: torch.int32, wp.int64: torch.int64}
_DEVICES: dict[torch.device, object] = {}  # torch device -> Warp device


def _device(device: torch.device):
    _DEVICES[device] = wp.device_from_torch(device)
    return _DEVICES[device]


def _launch(kernel, dim: int, inputs: list, device: torch.device, **kwargs) -> None:
    if dim == 0:
        return
    stream = wp.stream_from_torch(device) if device.type == "cuda" else None
    wp_device = _DEVICES.get(device) or _device(device)
    ensure_loaded(kernel, wp_device)
    wp.launch(kernel, dim=dim, inputs=inputs, device=wp_device, stream=stream, **kwargs)


def _tile_ranges(work: Tensor, parts: int) -> list[tuple[int, int]]:
    """Splits the global tile list into `parts` contiguous ranges of about equal work.

    Args:
        work: [tiles] positive cost estimate of each tile.
    """
    num_tiles = work.numel()
    if parts <= 1 or num_tiles < 2:
        return [(0, num_tiles)]
    # Plain Python lists: a few hundred tiles at most on the CPU path, too few for numpy's
    # per-call cost to pay off.
    total = list(itertools.accumulate(work.tolist()))
    cuts = []
    for k in range(1, parts):
        target = total[-1] * k / parts
        # tile `first` is the first whose running total reaches the target: cut before or
        # after it, whichever leaves the first part closer to the target
        first = bisect.bisect_left(total, target)
        before = total[first - 1] if first > 0 else 0
        after = total[min(first, num_tiles - 1)]
        cuts.append(first + 1 if after - target < target - before else first)
    bounds = sorted({0, num_tiles, *[min(max(c, 1), num_tiles - 1) for c in cuts]})
    return [(a, b - a) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def _binning(settings: RasterSettings, device: torch.device) -> str:
    """The binning: "counting" (serial counting sort, CPU only) or "sort" (a global key sort, any device)."""
    if settings.warp_binning == "auto":
        return "counting" if device.type == "cpu" else "sort"
    if settings.warp_binning == "counting" and device.type != "cpu":
        raise ValueError(
            "warp_binning='counting' relies on serial launches and runs on the CPU only; use 'sort' or "
            "'auto' on CUDA"
        )
    return settings.warp_binning


def _layout(settings: RasterSettings, device: torch.device) -> str:
    """Layout: "tile" (CPU, tiles of at most 16 px: one SIMD row each) or "pixel" (CUDA, larger tiles)."""
    if settings.warp_layout == "pixel":
        return "pixel"
    if settings.tile_size > T.LANES:
        if settings.warp_layout == "tile":
            raise ValueError(
                f"warp_layout='tile' handles tiles of at most {T.LANES} px (one SIMD row), got "
                f"tile_size={settings.tile_size}; use a smaller tile_size or 'auto'"
            )
        return "pixel"
    if settings.warp_layout == "tile":
        return "tile"
    return "tile" if device.type == "cpu" else "pixel"


def _row_buffers(settings: RasterSettings, device: torch.device, num_tiles: int, num_rows: int) -> list:
    """Scratch rows of the tile layout (``warp_tile_kernels``); empty for the pixel layout."""
    n = num_tiles * T.LANES if _layout(settings, device) == "tile" else 0
    rows = torch.empty(num_rows, n, T.LANES, dtype=torch.float32, device=device)
    ends = torch.empty(n, T.LANES, dtype=torch.int32, device=device)
    return [_arr(rows, T.vec16), _arr(ends, T.vec16i)]


def _launch_tiles(kernels, ranges, settings: RasterSettings, args: list, device: torch.device):
    """Launches a raster kernel over tile ranges, in parallel Python threads on CPU.

    Args:
        kernels: (tile-layout kernel, pixel-layout kernel); the layout follows settings/device.
    """
    layout = _layout(settings, device)
    kernel = kernels[0] if layout == "tile" else kernels[1]
    per_tile = 1 if layout == "tile" else settings.tile_size * settings.tile_size
    head = [settings.tile_size, settings.tiles_x, settings.tiles_x * settings.tiles_y,
            settings.width, settings.height]  # fmt: skip

    def run(r: tuple[int, int]) -> None:
        _launch(kernel, r[1] * per_tile, [r[0], *head, *args], device)

    if device.type == "cpu" and len(ranges) > 1:
        _run_parallel(kernel, [(r[1] * per_tile, [r[0], *head, *args]) for r in ranges], device)
    else:
        for r in ranges:
            run(r)


def _run_parallel(kernel, launches: list[tuple[int, list]], device: torch.device) -> None:
    """Runs CPU launches (dim, args) of ``kernel`` at once, one per thread (``run_launches``)."""
    run_launches(kernel, launches, _DEVICES.get(device) or _device(device))


def _cuts(total: int, unit: int, parts: int) -> list[int]:
    """0 = c_0 <= c_1 <= ... <= c_parts = total: about equal ranges cut at multiples of ``unit``.

    Kernels that accumulate per image (tile counts) cut at images, unit = N; kernels that
    accumulate per Gaussian (gradients summed over a scene's cameras) cut at scenes, unit = C N.
    Ranges cut that way write disjoint memory, so they run at once without atomics between them.
    """
    if parts <= 1 or unit <= 0 or total < 2 * unit:
        return [0, total]
    units = total // unit
    return [0, *[(units * k // parts) * unit for k in range(1, parts)], total]


def _launch_split(
    kernel, cuts: list[int], args: list, device: torch.device, min_part: int | None = None
) -> None:
    """Launches ``kernel(offset, *args)`` over the index ranges between ``cuts``, one thread each
    on the CPU when every range has at least ``min_part`` (default ``_MIN_SPLIT``) indices."""
    ranges = [(a, b - a) for a, b in itertools.pairwise(cuts) if b > a]
    min_part = _MIN_SPLIT if min_part is None else min_part
    if device.type != "cpu" or len(ranges) < 2 or min(n for _, n in ranges) < min_part:
        _launch(kernel, cuts[-1] - cuts[0], [cuts[0], *args], device)
    else:
        _run_parallel(kernel, [(n, [a, *args]) for a, n in ranges], device)


# Fewer indices per thread than this and a helper-thread hand-off (50-75 us, physgm.parallel)
# costs about what it saves: a CPU handles a few thousand pairs or entries in that time.
_MIN_SPLIT = 8192
# The fused projection and bounds (`project_bounds_kernel`) split like the rest, by pairs.
# Binning one image on two threads: each walks every pair in depth order, skips those whose tiles
# are the other's (a read of 8 bytes) and writes its share of the entries, so a small image gains
# nothing from the split.
_MIN_SPLIT_BIN = 8192
# The projection's vector-Jacobian product costs more per pair, so it splits from fewer pairs.
_MIN_SPLIT_VJP = 2048

_FORWARD = (T.raster_forward_tile_kernel, R.raster_forward_pixel_kernel)
_BACKWARD = (T.raster_backward_tile_kernel, R.raster_backward_pixel_kernel)


def _project_bounds(args: list, num_pairs: int, num_tiles: int, threads: int, device: torch.device) -> Tensor:
    """Runs ``project_bounds_kernel(offset, *args, tile_counts)`` over all pairs and returns the
    [num_tiles] int32 tile counts. On the CPU the pairs split into ``threads`` ranges (from
    ``_MIN_SPLIT`` pairs each), each counting into its own row; the rows' sum is the same in any
    split, so one image's Gaussians split as well as many images do."""
    cuts = _cuts(num_pairs, 1, threads)
    ranges = [(a, b - a) for a, b in itertools.pairwise(cuts) if b > a]
    if device.type != "cpu" or len(ranges) < 2 or min(n for _, n in ranges) < _MIN_SPLIT:
        ranges = [(0, num_pairs)]
    rows = torch.zeros(len(ranges), num_tiles, dtype=torch.int32, device=device)
    launches = [(n, [a, *args, _arr(rows[k], wp.int32)]) for k, (a, n) in enumerate(ranges)]
    if len(launches) > 1:
        _run_parallel(K.project_bounds_kernel, launches, device)
        return rows.sum(0, dtype=torch.int32)
    _launch(K.project_bounds_kernel, *launches[0], device)
    return rows[0]


def _pairs_in_order(order: Tensor, pair_in: list, spans: Tensor, threads: int, device: torch.device) -> list:
    """``bin_entries_kernel``'s per-row inputs: the pairs ``order`` [E] lists, their data and
    span of tiles copied in that order by ``gather_pairs_kernel`` (split over threads by rows)."""
    num = order.numel()
    shapes = ((2,), (3,), (), (2,), (), (3,))  # means2d, conics, qmax, extents, opacities, colours
    dtypes = (wp.vec2, wp.vec3, wp.float32, wp.vec2, wp.float32, wp.vec3)
    out = [_arr(torch.empty(num, *k, device=device), d) for k, d in zip(shapes, dtypes, strict=True)]
    out.append(_arr(torch.empty(num, 2, dtype=torch.int32, device=device), wp.vec2i))
    order_arr = _arr(order, wp.int64)
    args = [order_arr, *pair_in, _arr(spans, wp.vec2i), *out]
    _launch_split(K.gather_pairs_kernel, _cuts(num, 1, threads), args, device)
    return [order_arr, *out]


def _projection_args(means, quats, scales, opacities, viewmats, Ks, num_n, num_c, s) -> list:
    """Leading arguments of `project_bounds_kernel` and `project_vjp_kernel` (after the offset)."""
    return [_arr(means, wp.vec3), _arr(quats, wp.vec4), _arr(scales, wp.vec3),
            _arr(opacities, wp.float32), _arr(viewmats, wp.mat44), _arr(Ks, wp.mat33),
            num_n, num_c, s.width, s.height, s.near_plane, s.far_plane, s.eps2d]  # fmt: skip


def _projection_outputs(means2d, conics, depths) -> list:
    return [_arr(means2d, wp.vec2), _arr(conics, wp.vec3), _arr(depths, wp.float32)]


def _entry_arrays(entries: list[Tensor]) -> list[wp.array]:
    """Warp views of the gathered entry data: means2d, conics, opacity, qmax, colour, extent."""
    dtypes = (wp.vec2, wp.vec3, wp.float32, wp.float32, wp.vec3, wp.vec2)
    return [_arr(x, dtype) for x, dtype in zip(entries, dtypes, strict=True)]


class _RasterizeWarp(torch.autograd.Function):
    """Differentiable w.r.t. means, quats, scales, opacities and colours (float32, flattened)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, viewmats, Ks, settings, num_c):
        device = means.device
        num_bn, num_i = means.shape[0], viewmats.shape[0]
        num_n = num_bn * num_c // num_i
        num_pairs = num_i * num_n
        s = settings
        proj_in = _projection_args(means, quats, scales, opacities, viewmats, Ks, num_n, num_c, s)
        means2d = means.new_empty(num_pairs, 2)
        conics = means.new_empty(num_pairs, 3)
        depths = means.new_empty(num_pairs)
        proj_out = _projection_outputs(means2d, conics, depths)

        # --- binning: box per pair and entries per tile, then entries in (image, tile, depth) order ---
        tiles_per_image = s.tiles_x * s.tiles_y
        extents = means.new_empty(num_pairs, 2)
        qmax = means.new_empty(num_pairs)
        counts = torch.empty(num_pairs, dtype=torch.int32, device=device)
        spans = torch.empty(num_pairs, 2, dtype=torch.int32, device=device)
        bounds = [_arr(extents, wp.vec2), _arr(qmax, wp.float32), _arr(counts, wp.int32)]
        threads = s.num_threads if device.type == "cpu" else 1
        image_cuts = _cuts(num_pairs, num_n, threads)
        tile_counts = _project_bounds(
            [*proj_in, s.tile_size, s.tiles_x, tiles_per_image, *proj_out, *bounds, _arr(spans, wp.vec2i)],
            num_pairs,
            num_i * tiles_per_image,
            threads,
            device,
        )
        # forward split by entry count (+1: empty tiles are not free); binning within an image
        # splits by the same ranges, so each thread writes the entries it will read. The backward
        # split uses the pixel tests the forward counted, since its cost follows the composited pairs.
        tile_work = tile_counts + 1
        tile_ranges = _tile_ranges(tile_work, threads)
        tile_end = torch.cumsum(tile_counts, dim=0, dtype=torch.int32)
        tile_start = tile_end - tile_counts
        num_entries = int(tile_end[-1])
        e_pair = torch.empty(num_entries, dtype=torch.int64, device=device)
        e_gauss = torch.empty_like(e_pair)
        entries = [means.new_empty(num_entries, k) for k in (2, 3)]
        entries += [means.new_empty(num_entries), means.new_empty(num_entries)]
        entries += [means.new_empty(num_entries, 3), means.new_empty(num_entries, 2)]
        entry_arrs = _entry_arrays(entries)
        pair_in = [num_n, num_c, proj_out[0], proj_out[1], bounds[1], bounds[0], proj_in[3],
                   _arr(colors, wp.vec3)]  # fmt: skip
        entry_out = [_arr(e_pair, wp.int64), _arr(e_gauss, wp.int64), *entry_arrs]
        if num_entries and _binning(s, device) == "counting":
            # Only pairs that touch a tile are ordered. Their depths are > near_plane > 0, so the
            # float bits sort like the floats, and torch sorts integers by radix, far faster than
            # a comparison sort. Stable: equal depths keep pair order.
            emitted = torch.nonzero(counts, as_tuple=True)[0]
            by_depth = emitted[torch.sort(depths[emitted].view(torch.int32), stable=True)[1]]
            in_order = _pairs_in_order(by_depth, pair_in, spans, threads, device)
            cursor = _arr(tile_start.clone(), wp.int32)
            head = [s.width, s.height, s.tile_size, s.tiles_x, tiles_per_image]
            if len(image_cuts) > 2 and by_depth.numel() >= 2 * _MIN_SPLIT:
                # Each thread appends to the tiles of its own images.
                first_tiles = [c // num_n * tiles_per_image for c in image_cuts]
                own = list(itertools.pairwise(first_tiles))
            elif len(tile_ranges) > 1 and by_depth.numel() >= _MIN_SPLIT_BIN:
                own = [(t0, t0 + n) for t0, n in tile_ranges]  # the tiles each thread rasterises
            else:
                own = [(0, tile_counts.numel())]
            rest = [cursor, num_n, num_c, *in_order, *entry_out]
            launches = [(by_depth.numel(), [*head, lo, hi, *rest]) for lo, hi in own]
            if len(launches) > 1:
                _run_parallel(K.bin_entries_kernel, launches, device)
            else:
                _launch(K.bin_entries_kernel, *launches[0], device)
        elif num_entries:
            csum = torch.cumsum(counts, dim=0, dtype=torch.int32)
            entry_tile = torch.empty(num_entries, dtype=torch.int32, device=device)
            entry_pair = torch.empty(num_entries, dtype=torch.int32, device=device)
            _launch(K.emit_entries_kernel, num_pairs,
                    [proj_out[0], bounds[0], _arr(csum - counts, wp.int32), num_n, s.width, s.height,
                     s.tile_size, s.tiles_x, tiles_per_image, _arr(entry_tile, wp.int32),
                     _arr(entry_pair, wp.int32)], device)  # fmt: skip
            # depths are > 0 for every emitted pair, so their float bits sort like the floats
            depth_bits = depths.view(torch.int32).to(torch.int64)
            keys = (entry_tile.to(torch.int64) << 32) | depth_bits[entry_pair.to(torch.int64)]
            order = torch.sort(keys, stable=True)[1]  # stable: equal depths keep Gaussian order
            _launch(K.gather_entries_kernel, num_entries,
                    [_arr(order, wp.int64), _arr(entry_pair, wp.int32), *pair_in, *entry_out],
                    device)  # fmt: skip

        num_pix = num_i * s.height * s.width
        rgb = means.new_zeros(num_pix, 3)
        trans = means.new_ones(num_pix)
        end = torch.zeros(num_pix, dtype=torch.int32, device=device)
        tiles = [_arr(tile_start, wp.int32), _arr(tile_end, wp.int32), *entry_arrs]
        composite = [_arr(trans, wp.float32), _arr(end, wp.int32)]
        if num_entries:
            _launch_tiles(_FORWARD, tile_ranges, s,
                          [*tiles, _arr(rgb, wp.vec3), *composite,
                           *_row_buffers(s, device, tile_counts.numel(), T.FWD_ROWS),
                           _arr(tile_work, wp.int32)], device)  # fmt: skip

        ctx.settings, ctx.ranges = s, _tile_ranges(tile_work, threads)  # tile_work: now pixel tests
        # The Warp views are kept for the backward (~5 us each to rebuild); save_for_backward
        # still holds the tensors, so an in-place change between the passes is reported.
        ctx.warp_views = (proj_in, tiles, composite)
        ctx.num_pairs, ctx.num_c, ctx.num_n = num_pairs, num_c, num_n
        ctx.save_for_backward(means, quats, scales, opacities, viewmats, Ks, tile_start, tile_end,
                              e_pair, e_gauss, *entries, trans, end)  # fmt: skip
        alpha = 1.0 - trans
        ctx.mark_non_differentiable(means2d, depths, extents, counts)
        return rgb, alpha, means2d, depths, extents, counts

    @staticmethod
    def backward(ctx, v_rgb, v_alpha, *_unused):
        with single_threaded_torch():
            return _RasterizeWarp._backward(ctx, v_rgb, v_alpha)

    @staticmethod
    def _backward(ctx, v_rgb, v_alpha):
        (means, quats, scales, opacities, viewmats, Ks, tile_start, tile_end, e_pair, e_gauss, *entries,
         trans, end) = ctx.saved_tensors  # fmt: skip
        s, device = ctx.settings, means.device
        num_bn, num_e = means.shape[0], e_pair.numel()
        num_pairs = ctx.num_pairs
        v_means, v_quats = torch.zeros_like(means), torch.zeros_like(quats)
        v_scales, v_opac = torch.zeros_like(scales), torch.zeros_like(opacities)
        v_colors = torch.zeros(num_bn, 3, dtype=means.dtype, device=device)
        if num_e == 0:
            return v_means, v_quats, v_scales, v_opac, v_colors, None, None, None, None

        v_e_means2d = means.new_zeros(num_e, 2)
        v_e_conics = means.new_zeros(num_e, 3)
        v_e_opac = means.new_zeros(num_e)
        v_e_colors = means.new_zeros(num_e, 3)
        proj_in, tiles, composite = ctx.warp_views
        v_entry = [_arr(v_e_means2d, wp.vec2), _arr(v_e_conics, wp.vec3), _arr(v_e_opac, wp.float32),
                   _arr(v_e_colors, wp.vec3)]  # fmt: skip
        _launch_tiles(_BACKWARD, ctx.ranges, s,
                      [*tiles, *composite,
                       _arr(v_rgb.reshape(-1, 3), wp.vec3), _arr(v_alpha.reshape(-1), wp.float32),
                       *_row_buffers(s, device, tile_start.numel(), T.BWD_ROWS), *v_entry],
                      device)  # fmt: skip
        # Both launches below sum into Gaussians over all cameras of a scene: threads take whole scenes.
        num_n = ctx.num_n
        threads = s.num_threads if device.type == "cpu" else 1
        scene_cuts = _cuts(num_pairs, ctx.num_c * num_n, threads)
        tiles_per_image = s.tiles_x * s.tiles_y
        entry_cuts = [0, *[int(tile_start[c // num_n * tiles_per_image]) for c in scene_cuts[1:-1]], num_e]
        v_means2d, v_conics = means.new_zeros(num_pairs, 2), means.new_zeros(num_pairs, 3)
        _launch_split(K.scatter_entry_grads_kernel, entry_cuts,
                      [_arr(e_pair, wp.int64), _arr(e_gauss, wp.int64), *v_entry, _arr(v_means2d, wp.vec2),
                       _arr(v_conics, wp.vec3), _arr(v_opac, wp.float32), _arr(v_colors, wp.vec3)],
                      device)  # fmt: skip
        # With one camera per scene a pair writes only its own Gaussian: any pair range will do.
        vjp_cuts = _cuts(num_pairs, 1, threads) if ctx.num_c == 1 else scene_cuts
        _launch_split(K.project_vjp_kernel, vjp_cuts,
                      [*proj_in, _arr(v_means2d, wp.vec2), _arr(v_conics, wp.vec3), _arr(v_means, wp.vec3),
                       _arr(v_quats, wp.vec4), _arr(v_scales, wp.vec3)],
                      device, min_part=_MIN_SPLIT_VJP)  # fmt: skip
        return v_means, v_quats, v_scales, v_opac, v_colors, None, None, None, None


def rasterize_warp(batch: SplatBatch, settings: RasterSettings) -> tuple[Tensor, Tensor, dict]:
    """Renders B x C images in one pass; returns rgb [B, C, H, W, 3] (no background), alpha."""
    wp.init()  # no-op after the first call
    num_b, num_c, num_n = batch.num_b, batch.num_c, batch.num_n
    dtype = batch.means.dtype

    def flat(x: Tensor, *tail: int) -> Tensor:
        # float32 is the kernels' type; the cast is part of the autograd graph
        return x.reshape(-1, *tail).to(torch.float32).contiguous()

    rgb, alpha, means2d, depths, extents, counts = _RasterizeWarp.apply(
        flat(batch.means, 3), flat(batch.quats, 4), flat(batch.scales, 3), flat(batch.opacities),
        flat(batch.colors, 3), flat(batch.viewmats, 4, 4), flat(batch.Ks, 3, 3), settings, num_c,
    )  # fmt: skip
    shape = (num_b, num_c, settings.height, settings.width)
    nonempty = counts.reshape(num_b, num_c, num_n) > 0
    meta = {
        "means2d": means2d.reshape(num_b, num_c, num_n, 2),  # px
        "depths": depths.reshape(num_b, num_c, num_n),  # m
        "radii": radii_px(extents.reshape(num_b, num_c, num_n, 2), nonempty),  # [B, C, N, 2]
        "n_visible": nonempty.sum(-1),  # [B, C]
        "n_intersections": counts.reshape(num_b, num_c, num_n).sum(-1, dtype=torch.int64),
    }
    return rgb.reshape(*shape, 3).to(dtype), alpha.reshape(*shape, 1).to(dtype), meta
