"""Run two halves of a launch sequence on two CPU threads.

Warp runs a CPU kernel on one core and releases the GIL while it runs, so one extra Python
thread doubles the particle throughput on a two-core machine. The worker is a daemon thread that
executes a callable when released by a barrier; the main thread runs its own half meanwhile.
"""

from __future__ import annotations

import threading
from collections.abc import Callable


class PairWorker:
    """One helper thread executing ``task()`` while the caller runs its own half."""

    def __init__(self) -> None:
        self._start = threading.Barrier(2)
        self._done = threading.Barrier(2)
        self._task: Callable[[], None] | None = None
        self._error: BaseException | None = None
        self._stop = False
        self._thread = threading.Thread(target=self._loop, name="physgm-mpm-worker", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while True:
            self._start.wait()
            if self._stop:
                return
            try:
                self._task()
            except BaseException as err:  # re-raised in the caller's thread
                self._error = err
            self._done.wait()

    def run(self, task: Callable[[], None], own: Callable[[], None]) -> None:
        """Run ``task`` on the worker and ``own`` here; return when both are done."""
        self._task = task
        self._start.wait()
        try:
            own()
        finally:
            self._done.wait()
        if self._error is not None:
            err, self._error = self._error, None
            raise err

    def close(self) -> None:
        if self._thread.is_alive():
            self._stop = True
            self._start.wait()
            self._thread.join()
