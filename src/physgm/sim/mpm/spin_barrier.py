"""A barrier between two CPU threads that each replay a launch graph: a one-thread kernel that
spins on a shared counter.

The two-thread solver splits the particles in halves, and each sub-step needs both halves'
scatter before grid_update and grid_update before both halves' gather. Handing off through
Python costs ~110 us a sub-step (the GIL and two lock round-trips), as much as a whole one-thread
sub-step of ~600 particles. Inside the replays the two threads meet at ``barrier`` launches
instead, which cost well under a microsecond when the partner is already there.

State, one int64 array ``counter``: [0] arrivals, [1 + slot] barriers passed by thread ``slot``,
[3] abandoned (a thread waited past the time limit). Every thread passes every barrier, so
thread ``slot``'s n-th barrier opens when the arrivals reach 2 n. A thread that waits longer
than ``limit_cycles`` (the partner failed or never started) sets [3], and every barrier after that
returns at once; the caller checks [3] after the replay (``abandoned``) and raises instead of using
the half-stepped state. Past ``yield_after_cycles`` a waiting thread gives up its core at every
turn (``sched_yield``, Linux), for hosts with more busy threads than cores. Cycles are the x86
time-stamp counter; elsewhere a turn of the loop counts as 1000. The atomics are the
compiler's, so the counter lives in host memory: CPU only (a GPU runs the solver on one stream
and never needs this).
"""

from __future__ import annotations

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})

ABANDONED = 3  # index of the abandoned flag in the counter
# About 10 s at 3 GHz: far beyond any sub-step, short enough to end a replay whose partner died.
LIMIT_CYCLES = 30_000_000_000
# About 10 us: past this a waiting thread yields its core at every turn of the loop, so two solvers
# on two cores (data generation's worker processes) do not spin while their partners wait to run.
YIELD_AFTER_CYCLES = 30_000

_WAIT = """
#if defined(__CUDA_ARCH__)
    return;
#else
    long long* c = reinterpret_cast<long long*>(counter.data);
    if (__atomic_load_n(c + ABANDONED, __ATOMIC_ACQUIRE) != 0) {
        return;
    }
    const long long mine = c[1 + slot] + 1;  // this thread's own count: no other thread writes it
    c[1 + slot] = mine;
    __atomic_fetch_add(c, 1LL, __ATOMIC_ACQ_REL);
#if defined(__linux__)
    extern int physgm_sched_yield() __asm__("sched_yield");
#endif
#if defined(__x86_64__) || defined(__i386__)
    const unsigned long long start = __builtin_ia32_rdtsc();
#else
    unsigned long long turns = 0;
#endif
    while (__atomic_load_n(c, __ATOMIC_ACQUIRE) < 2 * mine) {
#if defined(__x86_64__) || defined(__i386__)
        const unsigned long long waited = __builtin_ia32_rdtsc() - start;
        __builtin_ia32_pause();
#else
        // No cycle counter user code may read everywhere: count about 1000 cycles a turn.
        const unsigned long long waited = 1000ULL * turns++;
#endif
        if (waited > static_cast<unsigned long long>(limit_cycles)) {
            __atomic_store_n(c + ABANDONED, 1LL, __ATOMIC_RELEASE);
            return;
        }
#if defined(__linux__)
        if (waited > static_cast<unsigned long long>(yield_after_cycles)) {
            physgm_sched_yield();  // the partner may be waiting for this core
        }
#endif
    }
#endif
""".replace("ABANDONED", str(ABANDONED))


@wp.func_native(_WAIT)
def wait_for_partner(
    counter: wp.array(dtype=wp.int64), slot: int, limit_cycles: wp.int64, yield_after_cycles: wp.int64
): ...


@wp.kernel
def barrier(
    counter: wp.array(dtype=wp.int64), slot: int, limit_cycles: wp.int64, yield_after_cycles: wp.int64
):
    """Launch with dim 1: returns when both threads have arrived (or the wait was abandoned)."""
    wait_for_partner(counter, slot, limit_cycles, yield_after_cycles)


def new_counter(device) -> wp.array:
    """A fresh barrier state (all zero)."""
    return wp.zeros(4, dtype=wp.int64, device=device)


def abandoned(counter: wp.array) -> bool:
    """Did a thread give up waiting at a barrier of ``counter``?"""
    return bool(np.asarray(counter.numpy())[ABANDONED] != 0)
