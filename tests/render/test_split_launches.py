"""The CPU splits the per-pair and per-entry launches of the warp backend over threads, at image,
scene or tile-range boundaries; the result must not depend on it."""

from __future__ import annotations

import pytest
import torch

from physgm.render import warp_backend
from physgm.render.batch import SplatBatch
from physgm.render.settings import RasterSettings
from physgm.render.torch_backend import rasterize_torch

SPLIT_KERNELS = {
    "project_bounds_kernel",
    "gather_pairs_kernel",
    "bin_entries_kernel",
    "scatter_entry_grads_kernel",
    "project_vjp_kernel",
}


def batched_scene(kit, num_b: int, num_c: int, num_n: int = 150, width: int = 40, height: int = 32) -> dict:
    """num_b different objects, each seen by its own num_c cameras ([B, N, ...], [B, C, ...], float32)."""
    objects = [kit.random_gaussians(num_n, seed=10 + b) for b in range(num_b)]
    cameras = [kit.orbit_cameras(num_c, width, height, seed=b) for b in range(num_b)]
    scene = {k: torch.stack([o[k] for o in objects]).float() for k in kit.GRAD_KEYS}
    scene["viewmats"] = torch.stack([c[0] for c in cameras]).float()
    scene["Ks"] = torch.stack([c[1] for c in cameras]).float()
    return scene


def render(scene: dict, fn, settings: RasterSettings):
    """rgb, alpha and the gradients of a fixed random loss."""
    leaves = {
        k: scene[k].clone().requires_grad_() for k in ("means", "quats", "scales", "opacities", "colors")
    }
    rgb, alpha, _ = fn(SplatBatch(*leaves.values(), scene["viewmats"], scene["Ks"]), settings)
    gen = torch.Generator().manual_seed(3)
    loss = (rgb * torch.randn(rgb.shape, generator=gen)).sum() + (
        alpha * torch.randn(alpha.shape, generator=gen)
    ).sum()
    loss.backward()
    return rgb.detach(), alpha.detach(), {k: v.grad for k, v in leaves.items()}


@pytest.mark.parametrize(
    ("num_b", "num_c", "threads"), [(3, 2, 2), (2, 3, 3), (1, 3, 2), (2, 1, 2), (1, 1, 2)]
)
def test_split_launches_match_one_thread_and_the_torch_twin(kit, monkeypatch, num_b, num_c, threads):
    scene = batched_scene(kit, num_b, num_c)
    serial = render(scene, warp_backend.rasterize_warp, RasterSettings(40, 32, num_threads=1))

    split = []
    run_parallel = warp_backend._run_parallel

    def recording(kernel, launches, device):
        split.append((kernel.key, len(launches)))
        if kernel.key == "bin_entries_kernel":
            bin_dims.append([dim for dim, _ in launches])
        run_parallel(kernel, launches, device)

    bin_dims = []

    monkeypatch.setattr(warp_backend, "_MIN_SPLIT", 1)  # split even these small launches
    monkeypatch.setattr(warp_backend, "_MIN_SPLIT_BIN", 1)
    monkeypatch.setattr(warp_backend, "_MIN_SPLIT_VJP", 1)
    monkeypatch.setattr(warp_backend, "_run_parallel", recording)
    parallel = render(scene, warp_backend.rasterize_warp, RasterSettings(40, 32, num_threads=threads))

    # bounds and the depth-ordered copy by pairs; binning always (by images, or by the raster's
    # tile ranges within one image); per scene: with 2 or more scenes, and the projection's
    # gradient with one camera per scene (a pair then writes only its own Gaussian)
    expected = {"project_bounds_kernel", "gather_pairs_kernel", "bin_entries_kernel"}
    if num_b > 1:
        expected |= {"scatter_entry_grads_kernel", "project_vjp_kernel"}
    if num_c == 1:
        expected |= {"project_vjp_kernel"}
    assert {key for key, parts in split if key in SPLIT_KERNELS and parts > 1} == expected
    if num_b * num_c == 1:  # one image: binned by the raster's tile ranges, one a thread
        (dims,) = bin_dims
        assert len(dims) == threads
    for a, b in zip(serial[:2], parallel[:2], strict=True):
        assert torch.equal(a, b)  # each pixel and each Gaussian's sum is computed by one thread, in order
    for name in serial[2]:
        assert torch.equal(serial[2][name], parallel[2][name]), name

    rgb_t, alpha_t, grads_t = render(scene, rasterize_torch, RasterSettings(40, 32))
    assert alpha_t.max() > 0.5
    assert (parallel[0] - rgb_t).abs().max() <= 1e-4
    assert (parallel[1] - alpha_t).abs().max() <= 1e-4
    for name, ref in grads_t.items():
        assert (parallel[2][name] - ref).norm() <= 1e-3 * ref.norm(), name


def test_cuts_fall_on_units():
    assert warp_backend._cuts(12, 4, 2) == [0, 4, 12]  # 3 scenes of 4 pairs: 1 + 2
    assert warp_backend._cuts(12, 4, 3) == [0, 4, 8, 12]
    assert warp_backend._cuts(4, 4, 2) == [0, 4]  # one scene cannot be split
    assert warp_backend._cuts(0, 0, 2) == [0, 0]  # no Gaussians
    assert warp_backend._cuts(7, 1, 1) == [0, 7]


def test_binning_by_tile_ranges_writes_each_tile_once_and_only_its_own():
    """Launches of `bin_entries_kernel` over tile ranges [lo, hi), run one after another, give the
    entries of one launch over all tiles, and each leaves every other tile's cursor alone."""
    import warp as wp

    from physgm.render import warp_kernels as K
    from physgm.render.projection import tile_rects

    gen = torch.Generator().manual_seed(5)
    num_n, width, height, tile = 300, 64, 48, 16
    settings = RasterSettings(width, height, tile_size=tile)
    tiles_x, tiles = settings.tiles_x, settings.tiles_x * settings.tiles_y
    means2d = torch.rand(num_n, 2, generator=gen) * torch.tensor([width + 20.0, height + 20.0]) - 10.0
    extents = torch.rand(num_n, 2, generator=gen) * 20.0
    rect, nonempty = tile_rects(means2d, extents, torch.ones(num_n, dtype=torch.bool), settings)
    tile_counts = torch.zeros(tiles, dtype=torch.int32)
    for (x0, x1, y0, y1), keep in zip(rect.tolist(), nonempty.tolist(), strict=True):
        for ty in range(y0, y1 + 1):
            for tx in range(x0, x1 + 1):
                tile_counts[ty * tiles_x + tx] += int(keep)
    tile_end = torch.cumsum(tile_counts, 0, dtype=torch.int32)
    tile_start = tile_end - tile_counts
    order = torch.randperm(num_n, generator=gen)
    pair_in = [
        means2d,
        torch.rand(num_n, 3, generator=gen),
        torch.rand(num_n, generator=gen),
        extents,
        torch.rand(num_n, generator=gen),
        torch.rand(num_n, 3, generator=gen),
    ]
    m = int(tile_end[-1])
    # the pairs in depth order, as gather_pairs_kernel leaves them (one image, one camera: g = pid)
    in_order = [x[order] for x in pair_in]
    spans = torch.stack([rect[:, 2] * tiles_x + rect[:, 0], rect[:, 3] * tiles_x + rect[:, 1]], 1)
    spans = spans.int()[order].contiguous()

    def bin_ranges(ranges):
        cursor = tile_start.clone()
        out = [torch.full((m,), -1, dtype=torch.int64), torch.full((m,), -1, dtype=torch.int64)]
        out += [torch.zeros(m, k) if k > 1 else torch.zeros(m) for k in (2, 3, 1, 1, 3, 2)]
        dtypes = (wp.vec2, wp.vec3, wp.float32, wp.vec2, wp.float32, wp.vec3)
        row_args = [warp_backend._arr(x, d) for x, d in zip(in_order, dtypes, strict=True)]
        row_args.append(warp_backend._arr(spans, wp.vec2i))
        out_dtypes = (wp.int64, wp.int64, wp.vec2, wp.vec3, wp.float32, wp.float32, wp.vec3, wp.vec2)
        out_args = [warp_backend._arr(x, d) for x, d in zip(out, out_dtypes, strict=True)]
        for lo, hi in ranges:
            warp_backend._launch(
                K.bin_entries_kernel,
                num_n,
                [
                    width,
                    height,
                    tile,
                    tiles_x,
                    tiles,
                    lo,
                    hi,
                    warp_backend._arr(cursor, wp.int32),
                    num_n,
                    1,
                    warp_backend._arr(order, wp.int64),
                    *row_args,
                    *out_args,
                ],
                torch.device("cpu"),
            )
        return cursor, out

    cursor_all, out_all = bin_ranges([(0, tiles)])
    assert torch.equal(cursor_all, tile_end) and (out_all[0] >= 0).all()
    for cut in (1, 5, tiles - 1):
        cursor, out = bin_ranges([(0, cut), (cut, tiles)])
        assert torch.equal(cursor, tile_end), cut  # no tile appended to twice
        for a, b in zip(out, out_all, strict=True):
            assert torch.equal(a, b), cut
        cursor, _ = bin_ranges([(cut, tiles)])
        assert torch.equal(cursor[:cut], tile_start[:cut]) and torch.equal(cursor[cut:], tile_end[cut:])
