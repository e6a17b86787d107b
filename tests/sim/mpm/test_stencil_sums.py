"""The stencil's native sums against numpy: the CPU vector form the solver runs here, and the
portable form CUDA compiles, built on the CPU from the same snippet text."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from physgm.sim.mpm.stencil_sums import (
    GATHER_PORTABLE,
    SCATTER_PORTABLE,
    gather_moments,
    mat48,
    scatter_affine,
    vec8,
)

SHAPE = (5, 6, 7)  # grid nodes
BASE = (1, 2, 3)  # the stencil's base node


@wp.func_native(GATHER_PORTABLE)
def gather_portable(grid: wp.array(dtype=vec8), row: int, nyz: int, nz: int, w: wp.mat33) -> mat48: ...


@wp.func_native(SCATTER_PORTABLE)
def scatter_portable(
    grid: wp.array(dtype=vec8),
    row: int,
    nyz: int,
    nz: int,
    w: wp.mat33,
    b: vec8,
    di: vec8,
    dj: vec8,
    dk: vec8,
): ...


@wp.kernel
def gather_both(
    grid: wp.array(dtype=vec8), row: int, nyz: int, nz: int, w: wp.mat33, out: wp.array(dtype=mat48)
):
    out[0] = gather_moments(grid, row, nyz, nz, w)
    out[1] = gather_portable(grid, row, nyz, nz, w)


@wp.kernel
def scatter_into(
    grid: wp.array(dtype=vec8),
    row: int,
    nyz: int,
    nz: int,
    w: wp.mat33,
    terms: wp.array(dtype=vec8),  # b, di, dj, dk
    portable: int,
):
    if portable == 0:
        scatter_affine(grid, row, nyz, nz, w, terms[0], terms[1], terms[2], terms[3])
    else:
        scatter_portable(grid, row, nyz, nz, w, terms[0], terms[1], terms[2], terms[3])


def weights(rng: np.random.Generator) -> np.ndarray:
    """Quadratic B-spline weights of a random fractional offset: row = node offset, column = axis."""
    fx = rng.uniform(0.5, 1.5, 3)
    return np.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]).astype(np.float32)


def stencil_nodes(w: np.ndarray):
    """(offset, flat node index, weight) of the 27 stencil nodes."""
    for i in range(3):
        for j in range(3):
            for k in range(3):
                flat = np.ravel_multi_index((BASE[0] + i, BASE[1] + j, BASE[2] + k), SHAPE)
                yield np.array([i, j, k], np.float64), flat, float(w[i, 0]) * float(w[j, 1]) * float(w[k, 2])


def launch_args(w: np.ndarray) -> tuple:
    row = int(np.ravel_multi_index(BASE, SHAPE))
    return row, SHAPE[1] * SHAPE[2], SHAPE[2], wp.mat33(*w.flatten().tolist())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gather_moments_match_numpy(seed):
    rng = np.random.default_rng(seed)
    grid = rng.normal(size=(int(np.prod(SHAPE)), 8)).astype(np.float32)
    w = weights(rng)
    expected = np.zeros((4, 8))
    for offset, flat, wn in stencil_nodes(w):
        expected += np.outer(np.concatenate([[1.0], offset]), wn * grid[flat].astype(np.float64))
    out = wp.zeros(2, dtype=mat48, device="cpu")
    grid_wp = wp.array(grid, dtype=vec8, device="cpu")
    wp.launch(gather_both, dim=1, inputs=[grid_wp, *launch_args(w), out], device="cpu")
    cpu_form, portable_form = out.numpy()
    np.testing.assert_allclose(cpu_form, expected, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(portable_form, expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("portable", [0, 1])
def test_scatter_affine_adds_to_every_stencil_node_and_no_other(portable):
    rng = np.random.default_rng(3 + portable)
    start = rng.normal(size=(int(np.prod(SHAPE)), 8)).astype(np.float32)
    terms = rng.normal(size=(4, 8)).astype(np.float32)
    w = weights(rng)
    expected = start.astype(np.float64)
    for offset, flat, wn in stencil_nodes(w):
        expected[flat] += wn * (terms[0] + offset @ terms[1:].astype(np.float64))
    grid = wp.array(start, dtype=vec8, device="cpu")
    wp.launch(
        scatter_into,
        dim=1,
        inputs=[grid, *launch_args(w), wp.array(terms, dtype=vec8, device="cpu"), portable],
        device="cpu",
    )
    np.testing.assert_allclose(grid.numpy(), expected, rtol=1e-5, atol=1e-5)
    assert np.count_nonzero(np.any(grid.numpy() != start, axis=1)) == 27
