"""Thread-safe first load of Warp modules (physgm.warp_runtime)."""

import threading
import time

import numpy as np
import warp as wp

from physgm.warp_runtime import ensure_loaded


@wp.kernel(module="unique")
def _double(a: wp.array(dtype=float)):
    i = wp.tid()
    a[i] = 2.0 * a[i]


def test_concurrent_first_use_loads_the_module_one_thread_at_a_time():
    wp.init()
    module = _double.module
    original = module.load
    lock, cold, peak = threading.Lock(), [0], [0]

    def slow_cold_load(*args, **kwargs):
        is_cold = not module.execs  # nothing loaded yet: the unsafe part of Warp's first use
        if is_cold:
            with lock:
                cold[0] += 1
                peak[0] = max(peak[0], cold[0])
            time.sleep(0.05)  # widen the window in which a second thread could enter
        try:
            return original(*args, **kwargs)
        finally:
            if is_cold:
                with lock:
                    cold[0] -= 1

    module.load = slow_cold_load
    barrier = threading.Barrier(8)
    arrays = [wp.array(np.full(16, i, np.float32), dtype=float, device="cpu") for i in range(8)]
    errors = []

    def worker(i: int) -> None:
        barrier.wait()  # all threads reach the first use together
        try:
            ensure_loaded(_double, "cpu")
            wp.launch(_double, 16, [arrays[i]], device="cpu")
        except Exception as err:  # noqa: BLE001 - reported below
            errors.append(err)

    try:
        threads = [threading.Thread(target=worker, args=(i,)) for i in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        del module.load
    assert not errors
    assert peak[0] == 1  # never two cold loads at once
    for i, a in enumerate(arrays):
        np.testing.assert_array_equal(a.numpy(), np.full(16, 2.0 * i, np.float32))


def test_preload_covers_every_kernel_module_of_the_package():
    """A new file with Warp kernels must join KERNEL_MODULES, or preload misses it."""
    from pathlib import Path

    import physgm
    from physgm.warp_runtime import _READY, KERNEL_MODULES, preload

    root = Path(physgm.__file__).parent
    found = {
        "physgm." + ".".join(p.relative_to(root).with_suffix("").parts)
        for p in root.rglob("*.py")
        if "@wp.kernel" in p.read_text()
    }
    assert found == set(KERNEL_MODULES)
    preload("cpu")
    assert len({key[0] for key in _READY}) >= len(KERNEL_MODULES)
