"""Helper threads: the MPM solver's two-thread hand-off and the rasteriser's tile split."""

from __future__ import annotations

import threading

import pytest

from physgm.parallel import HelperThread, PairWorker, helpers_for_this_thread, run_split


def test_runs_both_halves_on_two_threads():
    worker = PairWorker()
    seen = []
    try:
        for i in range(50):
            worker.run(
                lambda i=i: seen.append(("task", i, threading.get_ident())),
                lambda i=i: seen.append(("own", i)),
            )
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


def test_run_split_runs_every_task_once_and_the_last_on_the_caller():
    helpers = [HelperThread() for _ in range(3)]
    seen: dict[int, int] = {}
    try:
        for _ in range(20):
            seen.clear()
            run_split([lambda i=i: seen.__setitem__(i, threading.get_ident()) for i in range(4)], helpers)
            assert sorted(seen) == [0, 1, 2, 3]
            assert seen[3] == threading.get_ident()
            assert len({seen[i] for i in range(3)} | {seen[3]}) == 4  # four different threads
        with pytest.raises(ValueError, match="need 4 helpers"):
            run_split([lambda: None] * 5, helpers)
    finally:
        for h in helpers:
            h.close()


def test_run_split_waits_for_all_helpers_before_raising():
    helpers = [HelperThread(), HelperThread()]
    finished = []

    def slow():
        threading.Event().wait(0.05)
        finished.append("slow")

    try:
        with pytest.raises(KeyError):
            run_split([lambda: {}["missing"], slow, lambda: None], helpers)
        assert finished == ["slow"]  # the error surfaced only after the other helper was done
        run_split([slow, lambda: None], helpers)  # both helpers are usable again
    finally:
        for h in helpers:
            h.close()


def test_each_calling_thread_gets_its_own_helpers_and_dead_callers_are_cleaned_up():
    mine = helpers_for_this_thread(2)
    assert helpers_for_this_thread(1)[0] is mine[0]  # reused, not re-created
    theirs = []
    t = threading.Thread(target=lambda: theirs.extend(helpers_for_this_thread(2)))
    t.start()
    t.join()
    assert not {id(h) for h in theirs} & {id(h) for h in mine}
    # the next caller to register closes the helpers of the thread that has ended
    t2 = threading.Thread(target=lambda: helpers_for_this_thread(1))
    t2.start()
    t2.join()
    assert all(not h._thread.is_alive() for h in theirs)
    assert all(h._thread.is_alive() for h in mine)


def _fresh_python(code: str, env: dict[str, str]) -> str:
    import os
    import subprocess
    import sys

    clean = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    result = subprocess.run(
        [sys.executable, "-c", code], env={**clean, **env}, capture_output=True, text=True, check=True
    )
    return result.stdout.strip()


def test_importing_physgm_shortens_openmp_spinning_before_torch_loads():
    # libgomp reads GOMP_SPINCOUNT when torch loads it: `import physgm` must set it and must not
    # load torch itself, or the setting would come too late (physgm/__init__.py)
    code = "import sys, os, physgm; print('torch' in sys.modules, os.environ.get('GOMP_SPINCOUNT'))"
    assert _fresh_python(code, {}) == "False 100000"


def test_a_spin_count_the_user_set_is_kept():
    code = "import os, physgm; print(os.environ['GOMP_SPINCOUNT'])"
    assert _fresh_python(code, {"GOMP_SPINCOUNT": "1234"}) == "1234"


def test_the_spin_count_is_left_unset_when_torch_loaded_first():
    # too late to take effect, so the environment must not claim it
    code = "import os, torch, physgm; print(os.environ.get('GOMP_SPINCOUNT'))"
    assert _fresh_python(code, {}) == "None"
