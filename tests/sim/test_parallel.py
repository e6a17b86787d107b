"""The two-thread hand-off used by the CPU solver."""

from __future__ import annotations

import threading

import pytest

from physgm.sim.parallel import PairWorker


def test_runs_both_halves_on_two_threads():
    worker = PairWorker()
    seen = []
    try:
        for i in range(50):
            worker.run(lambda i=i: seen.append(("task", i, threading.get_ident())), lambda i=i: seen.append(("own", i)))
    finally:
        worker.close()
    tasks = [s for s in seen if s[0] == "task"]
    assert [s[1] for s in tasks] == list(range(50))
    assert len(seen) == 100
    assert {s[2] for s in tasks} != {threading.get_ident()}  # the task ran on the worker


def test_worker_error_is_raised_in_the_caller_and_the_worker_survives():
    worker = PairWorker()
    try:
        with pytest.raises(ZeroDivisionError):
            worker.run(lambda: 1 / 0, lambda: None)
        done = []
        worker.run(lambda: done.append(1), lambda: done.append(2))
        assert sorted(done) == [1, 2]
    finally:
        worker.close()
    with pytest.raises(RuntimeError, match="after close"):
        worker.run(lambda: None, lambda: None)
    worker.close()  # a second close is harmless
