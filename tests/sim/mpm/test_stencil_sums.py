"""The stencil's native sums against numpy: the CPU vector form the solver runs here, and the
portable form CUDA compiles, built on the CPU from the same snippet text, both on the grid's
blocked node layout (``grid_layout``)."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from physgm.sim.mpm.grid_layout import from_dense, stencil_offsets, to_dense
from physgm.sim.mpm.stencil_sums import (
    GATHER_PORTABLE,
    SCATTER_PORTABLE,
    gather_moments,
    mat48,
    scatter_affine,
    vec8,
)

SHAPE = (5, 6, 7)  # grid nodes: not whole blocks, so the layout's padding is in play
BASE = (1, 2, 3)  # the stencil's base node: its y and z layers cross from one block into the next


@wp.func_native(GATHER_PORTABLE)
def gather_portable(
    grid: wp.array(dtype=vec8), ox: wp.vec3i, oy: wp.vec3i, oz: wp.vec3i, w: wp.mat33
) -> mat48: ...


@wp.func_native(SCATTER_PORTABLE)
def scatter_portable(
    grid: wp.array(dtype=vec8),
    ox: wp.vec3i,
    oy: wp.vec3i,
    oz: wp.vec3i,
    w: wp.mat33,
    b: vec8,
    di: vec8,
    dj: vec8,
    dk: vec8,
): ...


@wp.kernel
def gather_both(
    grid: wp.array(dtype=vec8), base: wp.vec3i, shape: wp.vec3i, w: wp.mat33, out: wp.array(dtype=mat48)
):
    ox, oy, oz = stencil_offsets(base, shape)
    out[0] = gather_moments(grid, ox, oy, oz, w)
    out[1] = gather_portable(grid, ox, oy, oz, w)


@wp.kernel
def scatter_into(
    grid: wp.array(dtype=vec8),
    base: wp.vec3i,
    shape: wp.vec3i,
    w: wp.mat33,
    terms: wp.array(dtype=vec8),  # b, di, dj, dk
    portable: int,
):
    ox, oy, oz = stencil_offsets(base, shape)
    if portable == 0:
        scatter_affine(grid, ox, oy, oz, w, terms[0], terms[1], terms[2], terms[3])
    else:
        scatter_portable(grid, ox, oy, oz, w, terms[0], terms[1], terms[2], terms[3])


def weights(rng: np.random.Generator) -> np.ndarray:
    """Quadratic B-spline weights of a random fractional offset: row = node offset, column = axis."""
    fx = rng.uniform(0.5, 1.5, 3)
    return np.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]).astype(np.float32)


def stencil_nodes(w: np.ndarray):
    """(offset, node index, weight) of the 27 stencil nodes."""
    for i in range(3):
        for j in range(3):
            for k in range(3):
                node = (BASE[0] + i, BASE[1] + j, BASE[2] + k)
                yield np.array([i, j, k], np.float64), node, float(w[i, 0]) * float(w[j, 1]) * float(w[k, 2])


def launch_args(w: np.ndarray) -> tuple:
    return wp.vec3i(*BASE), wp.vec3i(*SHAPE), wp.mat33(*w.flatten().tolist())


def flat_blocked(dense: np.ndarray) -> wp.array:
    """[nx, ny, nz, 8] node values as the solver's flattened blocked node array."""
    return wp.array(from_dense(dense, SHAPE).reshape(-1, 8), dtype=vec8, device="cpu")


def test_blocked_layout_round_trips_and_keeps_each_block_in_one_piece():
    rng = np.random.default_rng(5)
    dense = rng.normal(size=(*SHAPE, 8)).astype(np.float32)
    blocked = from_dense(dense, SHAPE)
    assert blocked.shape == (2, 2, 2, 64, 8)
    np.testing.assert_array_equal(to_dense(blocked, SHAPE), dense)
    # Node (5 % 4, 6 % 4, 7 % 4) of block (1, 1, 1) would be outside the grid: padding, zero.
    assert blocked[1, 1, 1, 63].tolist() == [0.0] * 8
    # Node (1, 2, 3) is block (0, 0, 0), local 16 + 8 + 3.
    np.testing.assert_array_equal(blocked[0, 0, 0, 27], dense[1, 2, 3])
    with pytest.raises(ValueError, match="do not fit a grid"):
        from_dense(dense[:4], SHAPE)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gather_moments_match_numpy(seed):
    rng = np.random.default_rng(seed)
    grid = rng.normal(size=(*SHAPE, 8)).astype(np.float32)
    w = weights(rng)
    expected = np.zeros((4, 8))
    for offset, node, wn in stencil_nodes(w):
        expected += np.outer(np.concatenate([[1.0], offset]), wn * grid[node].astype(np.float64))
    out = wp.zeros(2, dtype=mat48, device="cpu")
    wp.launch(gather_both, dim=1, inputs=[flat_blocked(grid), *launch_args(w), out], device="cpu")
    cpu_form, portable_form = out.numpy()
    np.testing.assert_allclose(cpu_form, expected, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(portable_form, expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("portable", [0, 1])
def test_scatter_affine_adds_to_every_stencil_node_and_no_other(portable):
    rng = np.random.default_rng(3 + portable)
    start = rng.normal(size=(*SHAPE, 8)).astype(np.float32)
    terms = rng.normal(size=(4, 8)).astype(np.float32)
    w = weights(rng)
    expected = start.astype(np.float64)
    for offset, node, wn in stencil_nodes(w):
        expected[node] += wn * (terms[0] + offset @ terms[1:].astype(np.float64))
    grid = flat_blocked(start)
    wp.launch(
        scatter_into,
        dim=1,
        inputs=[grid, *launch_args(w), wp.array(terms, dtype=vec8, device="cpu"), portable],
        device="cpu",
    )
    out = to_dense(grid.numpy().reshape(*from_dense(start, SHAPE).shape[:4], 8), SHAPE)
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-5)
    assert np.count_nonzero(np.any(out != start, axis=-1)) == 27
