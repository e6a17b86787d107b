"""An unusable output folder stops train.py and simulate.py with one line, before any work."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from physgm.output_check import output_folder_problem

ROOT = Path(__file__).resolve().parents[1]


def test_a_usable_folder_passes_and_the_check_leaves_nothing_behind(tmp_path):
    target = tmp_path / "a" / "b" / "run"
    assert output_folder_problem(target) is None
    assert list(tmp_path.iterdir()) == []  # the folders it made to try are gone again
    (tmp_path / "existing").mkdir()
    assert output_folder_problem(tmp_path / "existing") is None
    assert list((tmp_path / "existing").iterdir()) == []


def test_uncreatable_folders_are_named_with_the_reason(tmp_path):
    assert "cannot create or write the output folder /proc/x" in output_folder_problem("/proc/x/run")
    (tmp_path / "notes.txt").write_text("a file")
    assert "notes.txt is a file" in output_folder_problem(tmp_path / "notes.txt" / "run")
    assert (
        output_folder_problem(tmp_path / "notes.txt")
        == f"the output folder {tmp_path / 'notes.txt'} is a file"
    )


def test_a_failed_write_removes_the_folders_the_check_made(tmp_path, monkeypatch):
    def refuse(self, data):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(Path, "write_bytes", refuse)
    problem = output_folder_problem(tmp_path / "new" / "run")
    assert (
        problem == f"cannot create or write the output folder {tmp_path / 'new' / 'run'} (Permission denied)"
    )
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_folder_is_refused(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir(mode=0o500)
    assert "Permission denied" in output_folder_problem(ro / "run")


def run_entry(script: str, *overrides: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, script, *overrides], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120
    )


@pytest.mark.parametrize(
    "command",
    [
        # Every other setting is broken too: the output folder must be the first thing checked.
        ("simulate.py", "input=missing.png", "ckpt=missing.ckpt"),
        ("train.py", "stage=pretrain", "data.root=/nonexistent", "synth=null"),
        ("train.py", "stage=dpo", "stage.init_ckpt=missing.ckpt"),
    ],
)
def test_entry_points_stop_with_one_line_before_any_work(command):
    done = run_entry(*command, "paths.output_dir=/proc/x/run")
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip() == (
        "error: cannot create or write the output folder /proc/x/run (No such file or directory); "
        "choose another paths.output_dir"
    )
    assert not Path("/proc/x").exists()
