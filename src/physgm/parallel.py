"""Helper threads for running Warp CPU launches side by side.

Warp runs a CPU kernel on one core and releases the GIL while it runs, so a few extra Python
threads put the other cores to work: the MPM solver splits its particles over two threads, the
rasteriser its tiles. The hand-off uses two plain locks per helper as binary semaphores, which
round-trip faster than ``threading.Barrier`` (a Condition underneath); the hand-off is a visible
share of a sub-step. A ``ThreadPoolExecutor`` submit + result adds a queue, a future and a
condition variable on top.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence

import warp as wp

from physgm.warp_runtime import ensure_loaded


class HelperThread:
    """One daemon thread that runs one task at a time: ``start(task)``, then ``wait()``."""

    def __init__(self, name: str = "physgm-helper") -> None:
        self._go = threading.Lock()  # released by the caller: a task is ready
        self._done = threading.Lock()  # released by the helper: the task has finished
        self._go.acquire()
        self._done.acquire()
        self._task: Callable[[], None] | None = None
        self._error: BaseException | None = None
        self._busy = False
        self._stop = False
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while True:
            self._go.acquire()
            if self._stop:
                return
            try:
                self._task()
            except BaseException as err:  # re-raised in the caller's thread by wait()
                self._error = err
            self._done.release()

    def start(self, task: Callable[[], None]) -> None:
        """Hand ``task`` to the helper; the caller must ``wait()`` before the next ``start``."""
        if self._stop:
            raise RuntimeError("HelperThread.start after close()")
        if self._busy:
            raise RuntimeError("HelperThread.start while the previous task is running; call wait() first")
        self._task, self._busy = task, True
        self._go.release()

    def wait(self) -> None:
        """Block until the task has finished; re-raise its exception, if any."""
        if not self._busy:
            return
        self._done.acquire()
        self._busy, self._task = False, None
        if self._error is not None:
            err, self._error = self._error, None
            raise err

    def close(self) -> None:
        if self._thread.is_alive() and not self._stop:
            self.wait()
            self._stop = True
            self._go.release()
            self._thread.join()


class PairWorker(HelperThread):
    """One helper thread executing ``task()`` while the caller runs its own half."""

    def __init__(self) -> None:
        super().__init__("physgm-mpm-worker")

    def run(self, task: Callable[[], None], own: Callable[[], None]) -> None:
        """Run ``task`` on the helper and ``own`` here; return when both are done."""
        if self._stop:
            raise RuntimeError("PairWorker.run after close()")
        self.start(task)
        try:
            own()
        finally:
            self.wait()


def run_split(tasks: Sequence[Callable[[], None]], helpers: Sequence[HelperThread]) -> None:
    """Run ``tasks[:-1]`` on ``helpers`` (one each) and the last task on the calling thread."""
    if len(tasks) > len(helpers) + 1:
        raise ValueError(f"{len(tasks)} tasks need {len(tasks) - 1} helpers, got {len(helpers)}")
    started = []
    try:
        for helper, task in zip(helpers, tasks[:-1], strict=False):
            helper.start(task)
            started.append(helper)
        if tasks:
            tasks[-1]()
    finally:
        errors = []
        for helper in started:
            try:
                helper.wait()
            except BaseException as err:
                errors.append(err)
        if errors:
            raise errors[0]


_HELPERS: dict[tuple[int, int], tuple[threading.Thread, list[HelperThread]]] = {}
_HELPERS_LOCK = threading.Lock()


def helpers_for_this_thread(count: int) -> list[HelperThread]:
    """``count`` helper threads owned by the calling thread (created on first use, then reused).

    Each calling thread gets its own helpers, so two threads rendering at once (e.g. DPO rollout
    workers) never hand tasks to the same helper. Keyed by process id as well: a forked child
    (a DataLoader worker) inherits the objects but not their threads, and would wait forever.
    Helpers of calling threads that have ended are closed when the next caller registers.
    """
    key = (os.getpid(), threading.get_ident())
    with _HELPERS_LOCK:
        owner, helpers = _HELPERS.get(key, (None, []))
        if owner is not threading.current_thread():  # new caller, or a reused thread id
            for k in [k for k, (t, _) in _HELPERS.items() if k[0] != key[0] or not t.is_alive()]:
                if k[0] == key[0]:
                    for h in _HELPERS[k][1]:
                        h.close()
                del _HELPERS[k]
            helpers = []
        while len(helpers) < count:
            helpers.append(HelperThread("physgm-raster"))
        _HELPERS[key] = (threading.current_thread(), helpers)
        return helpers[:count]


def run_launches(kernel, launches: Sequence[tuple[int, list]], device) -> None:
    """Run Warp launches of ``kernel``, one ``(dim, args)`` each, at once: all are packed here, so a
    helper needs the GIL only for a few microseconds (packing on the helpers made them wait for
    this thread's Python work), and the calling thread takes the last launch itself."""
    ensure_loaded(kernel, device)
    recorded = [wp.launch(kernel, dim, args, device=device, record_cmd=True) for dim, args in launches]
    run_split([launch.launch for launch in recorded], helpers_for_this_thread(len(recorded) - 1))
