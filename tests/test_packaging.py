"""Packaging: declared dependencies cover every import, package data is found, the wheel runs, set-up
checks the disk."""

from __future__ import annotations

import ast
import importlib
import importlib.util
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

import pytest
from packaging.requirements import Requirement

from physgm.resources import conf_dir, package_file, packaged_checkpoint

REPO = Path(__file__).resolve().parents[1]


def _declared() -> tuple[set[str], dict[str, set[str]]]:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    norm = lambda r: Requirement(r).name.lower().replace("_", "-")  # noqa: E731
    extras = {k: {norm(r) for r in v} for k, v in project["optional-dependencies"].items()}
    return {norm(r) for r in project["dependencies"]}, extras


def _imported_modules() -> dict[str, str]:
    """Top-level third-party modules imported anywhere in src/ and the entry points -> a file."""
    files = [p for p in (REPO / "src" / "physgm").rglob("*.py")] + [REPO / "simulate.py", REPO / "train.py"]
    out: dict[str, str] = {}
    for f in files:
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top != "physgm":
                    out.setdefault(top, str(f.relative_to(REPO)))
    return out


def test_every_import_is_a_declared_dependency():
    required, extras = _declared()
    dists = packages_distributions()
    optional = extras["gsplat"] | extras["view"]
    undeclared = {}
    for module, where in _imported_modules().items():
        # A module not installed here (gsplat without CUDA) is named like its distribution.
        names = {d.lower().replace("_", "-") for d in dists.get(module, [module])}
        if not names & (required | optional):
            undeclared[module] = where
    assert undeclared == {}, f"imported but not in pyproject.toml dependencies: {undeclared}"
    assert "gsplat" not in required and "viser" not in required  # heavy, optional: extras only


def test_config_tree_and_checkpoint_are_package_resources():
    wood = package_file("conf", "sim", "material", "wood.yaml")
    assert wood.is_file() and "name: wood" in wood.read_text()
    assert (conf_dir() / "simulate.yaml").is_file() and (conf_dir() / "sim" / "scene" / "drop.yaml").is_file()
    # In the checkout the package's conf/ is the repository's (one copy of every file).
    assert conf_dir().resolve() == (REPO / "conf").resolve()
    assert (
        packaged_checkpoint("checkpoints/physgm_tiny.ckpt").resolve()
        == (REPO / "checkpoints" / "physgm_tiny.ckpt").resolve()
    )
    assert packaged_checkpoint("elsewhere/physgm_tiny.ckpt") is None


def test_console_scripts_point_at_functions():
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    for name, target in scripts.items():
        module, func = target.split(":")
        assert importlib.util.find_spec(module) is not None, name
        assert callable(getattr(importlib.import_module(module), func)), name


@pytest.mark.slow
def test_wheel_in_a_fresh_venv_simulates_the_example_from_another_folder(capsys):
    """~2 min on 2 busy cores: build, venv, install --no-deps, physgm-simulate (scripts/check_install.py)."""
    spec = importlib.util.spec_from_file_location("check_install", REPO / "scripts" / "check_install.py")
    check = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(check)
    assert check.main([]) == 0, capsys.readouterr().out


@pytest.mark.parametrize("free_gb, refused", [(3, True), (50, False)])
def test_setup_refuses_a_first_install_on_a_full_disk_before_writing(tmp_path, free_gb, refused):
    """scripts/setup.sh checks the free space before it creates .venv; with enough it goes on (here it
    then fails at once, on a python that only reports its version, having passed the check)."""
    import os
    import shutil
    import subprocess

    (tmp_path / "scripts").mkdir()
    shutil.copy(REPO / "scripts" / "setup.sh", tmp_path / "scripts" / "setup.sh")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    df = bin_dir / "df"
    df.write_text(
        "#!/bin/sh\necho 'Filesystem 1024-blocks Used Available Capacity Mounted on'\n"
        f"echo '/dev/x 100000000 0 {free_gb * 1048576} 1% /'\n"
    )
    fake_python = bin_dir / "fake-python"
    fake_python.write_text("#!/bin/sh\necho 'fake-python: called' >&2\nexit 3\n")
    for f in (df, fake_python):
        f.chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}", "PYTHON": str(fake_python)}
    run = subprocess.run(
        ["bash", "scripts/setup.sh"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60
    )
    assert run.returncode != 0
    assert ("needs about 10 GB free here" in run.stderr) == refused, run.stderr
    assert ("fake-python: called" in run.stderr) == (not refused), run.stderr
    assert not (tmp_path / ".venv").exists()
