"""Run two halves of a launch sequence on two CPU threads.

Warp runs a CPU kernel on one core and releases the GIL while it runs, so one extra Python
thread puts the second core to work (1.3-1.6x the particle throughput measured on this
shared 2-vCPU machine, not 2x). The worker is a daemon thread that executes a callable when
handed one; the main thread runs its own half meanwhile.

The hand-off uses two plain locks as binary semaphores: ``threading.Barrier`` (a Condition
underneath) cost about 130 us per round trip here, two locks about 75 us, and an MPM sub-step
of 8k particles takes about 2 ms per thread, so the hand-off is a visible share of it.
"""

from __future__ import annotations

import threading
from collections.abc import Callable


class PairWorker:
    """One helper thread executing ``task()`` while the caller runs its own half."""

    def __init__(self) -> None:
        self._go = threading.Lock()  # released by the caller: a task is ready
        self._done = threading.Lock()  # released by the worker: the task has finished
        self._go.acquire()
        self._done.acquire()
        self._task: Callable[[], None] | None = None
        self._error: BaseException | None = None
        self._stop = False
        self._thread = threading.Thread(target=self._loop, name="physgm-mpm-worker", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while True:
            self._go.acquire()
            if self._stop:
                return
            try:
                self._task()
            except BaseException as err:  # re-raised in the caller's thread
                self._error = err
            self._done.release()

    def run(self, task: Callable[[], None], own: Callable[[], None]) -> None:
        """Run ``task`` on the worker and ``own`` here; return when both are done."""
        if self._stop:
            raise RuntimeError("PairWorker.run after close()")
        self._task = task
        self._go.release()
        try:
            own()
        finally:
            self._done.acquire()
        if self._error is not None:
            err, self._error = self._error, None
            raise err

    def close(self) -> None:
        if self._thread.is_alive() and not self._stop:
            self._stop = True
            self._go.release()
            self._thread.join()
