"""Where a grid node lies in memory: 4^3-node blocks, each block's 64 nodes side by side.

The grid's node arrays (the scatter's accumulators and ``grid_v``) are Warp arrays of shape
[bx, by, bz, 64] of ``vec8``: block (bi, bj, bk) = (i // 4, j // 4, k // 4) holds its nodes at
``local(i, j, k)`` = 16 (i % 4) + 4 (j % 4) + k % 4, so one block is 2 KB in one piece. A body
spread thin (sand's sheet after a landing, a splash) reaches a few nodes of many blocks; laid out
as one [nx, ny, nz] array each block was 16 rows of 128 bytes a page apart, and the grid update
walked them at the speed of memory latency (docs/measurements_sim.md section 33).

``load``, ``store`` and ``atomic_add_node`` take node indices; the stencil sums address a
particle's 27 nodes in the flattened array from one offset per axis (``stencil_offsets``), since
a flat index is a sum of a term in i, one in j and one in k. On the numpy side ``to_dense`` and
``from_dense`` convert to and from [nx, ny, nz, ...].
"""

from __future__ import annotations

import numpy as np
import warp as wp

from physgm.sim.mpm.stencil_sums import vec8

BLOCK = wp.constant(4)  # nodes per block side
BLOCK_NODES = wp.constant(64)  # nodes per block


def block_res(res: tuple[int, int, int]) -> tuple[int, int, int]:
    """Blocks per axis covering ``res`` nodes."""
    return tuple(-(-int(n) // BLOCK) for n in res)


def node_shape(res: tuple[int, int, int]) -> tuple[int, int, int, int]:
    """Shape of a node array of a grid of ``res`` nodes: blocks per axis, then 64 nodes."""
    return (*block_res(res), BLOCK_NODES)


def to_dense(a: np.ndarray, res: tuple[int, int, int]) -> np.ndarray:
    """[bx, by, bz, 64, ...] blocked node values -> [nx, ny, nz, ...]."""
    bx, by, bz = block_res(res)
    rest = a.shape[4:]
    d = a.reshape(bx, by, bz, BLOCK, BLOCK, BLOCK, *rest)
    d = d.transpose(0, 3, 1, 4, 2, 5, *range(6, 6 + len(rest)))
    d = d.reshape(bx * BLOCK, by * BLOCK, bz * BLOCK, *rest)
    return np.ascontiguousarray(d[: res[0], : res[1], : res[2]])


def from_dense(d: np.ndarray, res: tuple[int, int, int]) -> np.ndarray:
    """[nx, ny, nz, ...] node values -> [bx, by, bz, 64, ...] (the padding nodes zero)."""
    if tuple(d.shape[:3]) != tuple(res):
        raise ValueError(f"node values of shape {d.shape} do not fit a grid of {tuple(res)} nodes")
    bx, by, bz = block_res(res)
    rest = d.shape[3:]
    pad = np.zeros((bx * BLOCK, by * BLOCK, bz * BLOCK, *rest), dtype=d.dtype)
    pad[: res[0], : res[1], : res[2]] = d
    b = pad.reshape(bx, BLOCK, by, BLOCK, bz, BLOCK, *rest).transpose(
        0, 2, 4, 1, 3, 5, *range(6, 6 + len(rest))
    )
    return np.ascontiguousarray(b.reshape(bx, by, bz, BLOCK_NODES, *rest))


@wp.func
def local(i: int, j: int, k: int) -> int:
    """Index of node (i, j, k) inside its block."""
    return ((i & 3) << 4) | ((j & 3) << 2) | (k & 3)


@wp.func
def load(a: wp.array4d(dtype=vec8), i: int, j: int, k: int) -> vec8:
    return a[i >> 2, j >> 2, k >> 2, local(i, j, k)]


@wp.func
def store(a: wp.array4d(dtype=vec8), i: int, j: int, k: int, g: vec8):
    a[i >> 2, j >> 2, k >> 2, local(i, j, k)] = g


@wp.func
def atomic_add_node(a: wp.array4d(dtype=vec8), i: int, j: int, k: int, g: vec8):
    wp.atomic_add(a, i >> 2, j >> 2, k >> 2, local(i, j, k), g)


@wp.func
def axis_offsets(first: int, block_stride: int, node_stride: int) -> wp.vec3i:
    """Flat offsets of nodes first, first + 1, first + 2 along one axis."""
    out = wp.vec3i(0)
    for a in range(3):
        n = first + a
        out[a] = (n >> 2) * block_stride + (n & 3) * node_stride
    return out


@wp.func
def stencil_offsets(base: wp.vec3i, shape: wp.vec3i):
    """Per axis, the flat offsets of a stencil's three node layers from its base node: node
    (base + (a, b, c)) is at ``ox[a] + oy[b] + oz[c]`` of the flattened node array."""
    bz = (shape[2] + 3) >> 2
    by = (shape[1] + 3) >> 2
    ox = axis_offsets(base[0], by * bz * BLOCK_NODES, 16)
    oy = axis_offsets(base[1], bz * BLOCK_NODES, 4)
    oz = axis_offsets(base[2], BLOCK_NODES, 1)
    return ox, oy, oz
