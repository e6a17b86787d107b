"""The solver's node arrays on the CPU: zero, and memory only where something was written."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import warp as wp

from physgm.sim.mpm.grid_arrays import lazy_zeros
from physgm.sim.mpm.grid_layout import node_shape
from physgm.sim.mpm.kernels import vec8


def _resident_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/statm")
def test_node_arrays_take_memory_only_where_they_are_written():
    shape = node_shape((320, 320, 40))  # 4.1 M nodes, 131 MB
    lazy_zeros((1, 1, 1, 64), vec8, "cpu")  # Warp's start-up, outside the measurement
    before = _resident_bytes()
    a = lazy_zeros(shape, vec8, "cpu")
    assert a.shape == shape and a.dtype == vec8
    assert _resident_bytes() - before < 8 << 20  # wp.zeros writes all 131 MB
    block = np.arange(64 * 8, dtype=np.float32).reshape(64, 8)
    a[3, 4, 5].assign(block)  # one block of 64 nodes, 2 KB
    view = a.numpy()
    np.testing.assert_array_equal(view[3, 4, 5], block)
    assert not view[3, 4, 4].any() and not view[0, 0, 0].any() and not view[-1, -1, -1].any()
    del view, a


def test_only_float32_vectors_are_taken():
    with pytest.raises(TypeError, match="float32"):
        lazy_zeros((2, 2), wp.vec3d, "cpu")
