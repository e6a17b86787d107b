"""The Warp kernels of the tiled rasteriser before the raster step, by the name the backend uses.

Layout: images I = B * C are flattened; an (image, Gaussian) pair has index
pid = img * N + n and reads Gaussian g = (img // C) * N + n. After binning, every
(pair, tile) intersection is an *entry*; entries are sorted by (image, tile, depth) and their
data gathered into contiguous arrays, so a tile's Gaussians are entries
tile_start[t] .. tile_end[t] - 1.

The kernels live in two Warp modules (each file with kernels is one; ``physgm.warp_runtime``
lists them):
    warp_project_kernels  EWA projection of a pair (``project_kernel``) and its hand-written
                          backward (``project_vjp_kernel``)
    warp_bin_kernels      projection with the pair's box and tile counts
                          (``project_bounds_kernel``), the entries' ordering (emit + gather,
                          or the pairs copied in depth order and one counting-sort pass) and
                          the entries' gradients summed back (``scatter_entry_grads_kernel``)
The raster kernels are in `warp_raster_kernels.py` and `warp_tile_kernels.py`.
"""

from physgm.render.warp_bin_kernels import (
    bin_entries_kernel,
    emit_entries_kernel,
    gather_entries_kernel,
    gather_pairs_kernel,
    project_bounds_kernel,
    scatter_entry_grads_kernel,
)
from physgm.render.warp_project_kernels import project_kernel, project_vjp_kernel

__all__ = [
    "bin_entries_kernel",
    "emit_entries_kernel",
    "gather_entries_kernel",
    "gather_pairs_kernel",
    "project_bounds_kernel",
    "project_kernel",
    "project_vjp_kernel",
    "scatter_entry_grads_kernel",
]
