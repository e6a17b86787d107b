"""Thread-safe first use of Warp kernels.

Warp compiles and loads a module on its first launch, and that step is not thread-safe in
Warp 1.19: two threads launching kernels of the same not-yet-loaded module at once can fail
inside Warp (seen as ``KeyError: 1`` from ``Module.load``). physgm launches kernels from
several Python threads (rollout and evaluation workers, the CPU raster split), so every launch
site calls ``ensure_loaded`` first: the first use of a module on a device loads it under a
process-wide lock; later calls cost one set lookup.
"""

from __future__ import annotations

import threading

import warp as wp

_LOCK = threading.Lock()
_READY: set[tuple[int, str, int]] = set()


def ensure_loaded(kernel, device) -> None:
    """Load ``kernel``'s module on ``device`` (a Warp device or its name) unless already done."""
    device = wp.get_device(device)
    block_dim = 1 if device.is_cpu else int(kernel.module.options.get("block_dim", 256))
    key = (id(kernel.module), device.alias, block_dim)
    if key in _READY:
        return
    with _LOCK:
        if key not in _READY:
            kernel.module.load(device, block_dim)
            _READY.add(key)
