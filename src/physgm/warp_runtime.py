"""Thread-safe first use of Warp kernels.

Warp compiles and loads a module on its first launch, and that step is not thread-safe in
Warp 1.19: two threads launching kernels of the same not-yet-loaded module at once can fail
inside Warp (seen as ``KeyError: 1`` from ``Module.load``). physgm launches kernels from
several Python threads (rollout and evaluation workers, the CPU raster split), so every launch
site calls ``ensure_loaded`` first: the first use of a module on a device loads it under a
process-wide lock; later calls cost one set lookup.

The lock alone is not enough: a module's load (its first compile can take 10 s) also hashes the
modules it references, and a launch from one of those on another thread at that moment failed the
same way (a DPO run whose renderer module had just changed). Code that starts threads which
launch kernels calls ``preload`` first, so no module loads while the threads run.
"""

from __future__ import annotations

import importlib
import threading

import warp as wp

# CPU compiler flags of the MPM kernels: Warp's own (host features, its inlining limits) plus
# three of the fast-math rewrites. `-mreassociate` lets clang reorder sums (the stencil's
# vector sums, the constitutive algebra), `-fno-signed-zeros` drops the sign of zero, and
# `-ffp-contract=fast` fuses multiply-adds across statements. The MPM runs 1.1-1.3x faster on
# the CPU (docs/measurements_sim.md section 18); results move at round-off. Left out:
# `-ffinite-math-only` (part of `-ffast-math`), under which the solver's finiteness check in
# ``kernels.g2p_kernel`` would compile away, and `-freciprocal-math`, under which the Mohr-Coulomb sand
# heap of tests/sim/mpm/test_particle_ground.py collapsed to det F = 0 in its first frame.
FAST_MATH_FLAGS = "-mreassociate -fno-signed-zeros -ffp-contract=fast"
FAST_CPU_FLAGS = f"{wp.config.cpu_compiler_flags or '-march=native'} {FAST_MATH_FLAGS}"

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


# Every Python module of physgm that defines Warp kernels (each is one Warp module).
KERNEL_MODULES = (
    "physgm.render.warp_project_kernels",
    "physgm.render.warp_bin_kernels",
    "physgm.render.warp_raster_kernels",
    "physgm.sim.mpm.kernels",
    "physgm.sim.mpm.particle_ops",
    "physgm.sim.coupling",
    "physgm.sim.mpm.walls",
    "physgm.sim.mpm.observables",
    "physgm.sim.mpm.surface_friction",
    "physgm.sim.mpm.implicit_kernels",
    "physgm.sim.mpm.implicit_algebra",
    "physgm.sim.mpm.pressure_kernels",
    "physgm.sim.mpm.substep_params",
    "physgm.render.warp_tile_kernels",
    "physgm.sim.mpm.spin_barrier",
    "physgm.model.hull_kernels",
)
# Modules whose kernels only ever run on the CPU (C++ snippets written for the host compiler).
CPU_ONLY_MODULES = ("physgm.render.warp_tile_kernels", "physgm.sim.mpm.spin_barrier")


def preload(device="cpu") -> None:
    """Load (compiling on first use) every physgm Warp module on ``device``, from this thread."""
    is_cpu = wp.get_device(device).is_cpu
    for name in KERNEL_MODULES:
        if name in CPU_ONLY_MODULES and not is_cpu:
            continue
        module = importlib.import_module(name)
        kernel = next((v for v in vars(module).values() if isinstance(v, wp.Kernel)), None)
        if kernel is None:
            raise RuntimeError(f"{name} is listed in KERNEL_MODULES but defines no Warp kernel")
        ensure_loaded(kernel, device)
