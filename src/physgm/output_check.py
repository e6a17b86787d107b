"""Is the run's output folder usable? Asked before any work, by ``train.py`` and ``simulate.py`` alike.

Hydra creates the run folder (``hydra.run.dir``, set to ``paths.output_dir``) before it calls the
entry point, so a folder that cannot be created (``paths.output_dir=/proc/x``) used to end in
Hydra's ``FileNotFoundError`` traceback. ``CheckOutputFolder`` is a Hydra callback that runs
before that, and ``output_folder_problem`` is the check itself, for callers outside Hydra.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback


def output_folder_problem(path: str | Path) -> str | None:
    """Why ``path`` cannot be a run folder, or None when it can.

    Creates the missing folders and writes a probe file in the last one, then removes everything
    it made, so a failed check leaves nothing behind and a passed one changes nothing.
    """
    target = Path(path).expanduser().absolute()
    missing: list[Path] = []
    existing = target
    while not existing.exists() and existing != existing.parent:
        missing.append(existing)
        existing = existing.parent
    if existing == target and not target.is_dir():
        return f"the output folder {target} is a file"
    if not existing.is_dir():
        return f"{existing} is a file, so the output folder {target} cannot be made inside it"
    created: list[Path] = []
    try:
        for folder in reversed(missing):
            folder.mkdir()
            created.append(folder)
        probe = target / f".physgm-write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        return f"cannot create or write the output folder {target} ({err.strerror or err})"
    finally:
        for folder in reversed(created):
            try:
                folder.rmdir()
            except OSError:
                pass  # something else wrote into it meanwhile: leave it
    return None


class CheckOutputFolder(Callback):
    """Hydra callback: stop with ``error: ...`` (exit code 2) when the run or sweep folder is unusable.

    Runs before Hydra creates the folder, so nothing (no model load, no data, no simulation)
    has happened yet.
    """

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        self._check(config.hydra.run.dir)

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        self._check(config.hydra.sweep.dir)

    @staticmethod
    def _check(folder: str) -> None:
        problem = output_folder_problem(str(folder))
        if problem:
            print(f"error: {problem}; choose another paths.output_dir", file=sys.stderr)
            raise SystemExit(2)
