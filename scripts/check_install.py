"""Install the physgm wheel into a fresh venv and simulate the example photo from another folder.

    python scripts/check_install.py [--work DIR] [--keep]

Prints one JSON object (timings, where physgm was imported from, what the run wrote) and exits
1 if any step failed. What it proves and what it does not:

* The wheel is built from a copy of the checkout (``pip wheel --no-deps --no-build-isolation``, with the
  setuptools of the running interpreter) and installed with ``pip install --no-deps`` into a
  venv created with ``python -m venv`` (no ``--system-site-packages``): physgm, its console
  scripts, the config tree and the tiny checkpoint come from the wheel alone.
* The checkout is not on ``sys.path``: the run starts in an empty folder, without PYTHONPATH, and
  the script checks that ``physgm`` is imported from the venv.
* The third-party dependencies are NOT downloaded: a ``.pth`` file appends the running
  interpreter's site-packages (torch, warp, ... already installed at the pinned versions), since
  a fresh CPU torch alone takes minutes and gigabytes. The script checks instead that every
  requirement the wheel declares is present there at a version its specifier accepts;
  ``tests/test_packaging.py`` checks that every module the code imports is declared.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "jelly_cube.png"
# Small enough to take seconds: the point is that the installed package runs, not the video.
SIM_OVERRIDES = ["output.resolution=64", "output.frames=8", "output.progress=false"]
# Top-level folders that are not part of a build: version control, environments, data, outputs.
TOP_IGNORE = {".git", ".venv", "data", "outputs", "build", ".pytest_cache", ".ruff_cache", "wandb",
              "lightning_logs", "logs", "multirun"}  # fmt: skip


def _ignore(folder: str, names: list[str]) -> list[str]:
    top = Path(folder) == REPO
    return [n for n in names if (top and n in TOP_IGNORE) or n == "__pycache__" or n.endswith(".egg-info")]


CHECK_REQUIREMENTS = """
import importlib.metadata as md, json, physgm
from packaging.requirements import Requirement
bad = []
for text in md.requires("physgm") or []:
    req = Requirement(text)
    if req.marker is not None and not req.marker.evaluate({"extra": ""}):
        continue  # an extra (gsplat, view, dev)
    try:
        version = md.version(req.name)
    except md.PackageNotFoundError:
        bad.append(f"{req.name}: not installed")
        continue
    if not req.specifier.contains(version, prereleases=True):
        bad.append(f"{req.name} {version} does not satisfy {req.specifier}")
print(json.dumps({"physgm_file": physgm.__file__, "unmet_requirements": bad}))
"""


def _run(cmd: list[str], cwd: Path, env: dict[str, str] | None = None) -> tuple[float, str]:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(
            f"`{' '.join(cmd)}` failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
        )
    return time.perf_counter() - t0, proc.stdout


def check_install(work: Path) -> dict:
    """Build, install and run; returns the report (raises RuntimeError on a failed step)."""
    report: dict = {"work": str(work)}
    wheels, venv, elsewhere = work / "wheels", work / "venv", work / "elsewhere"
    elsewhere.mkdir(parents=True)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env.setdefault("OMP_NUM_THREADS", "1")

    # Build from a copy of the checkout: an in-tree build leaves build/ and *.egg-info behind.
    source = work / "source"
    shutil.copytree(REPO, source, symlinks=True, ignore=_ignore)
    t, _ = _run([sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation",
                 "-q", "-w", str(wheels)], cwd=elsewhere, env=env)  # fmt: skip
    report["build_s"] = round(t, 1)
    (wheel,) = wheels.glob("physgm-*.whl")
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
    report["wheel_mb"] = round(wheel.stat().st_size / 1e6, 1)
    report["wheel_materials"] = sum(n.startswith("physgm/conf/sim/material/") for n in names)
    report["wheel_has_checkpoint"] = "physgm/checkpoints/physgm_tiny.ckpt" in names

    t, _ = _run([sys.executable, "-m", "venv", str(venv)], cwd=elsewhere, env=env)
    report["venv_s"] = round(t, 1)
    py = venv / "bin" / "python"
    t, _ = _run([str(py), "-m", "pip", "install", "--no-deps", "-q", str(wheel)], cwd=elsewhere, env=env)
    report["install_s"] = round(t, 1)
    purelib = "import sysconfig; print(sysconfig.get_paths()['purelib'])"
    site = Path(subprocess.check_output([str(py), "-c", purelib], text=True).strip())
    # Only the dependencies: .pth files inside that folder (the checkout's editable install) are
    # not processed, because it is not a site directory of the new venv.
    (site / "zz_physgm_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")

    _, out = _run([str(py), "-c", CHECK_REQUIREMENTS], cwd=elsewhere, env=env)
    report.update(json.loads(out.strip().splitlines()[-1]))

    run_dir = elsewhere / "run"
    t, out = _run([str(venv / "bin" / "physgm-simulate"), f"input={EXAMPLE}", f"paths.output_dir={run_dir}",
                   *SIM_OVERRIDES], cwd=elsewhere, env=env)  # fmt: skip
    report["simulate_s"] = round(t, 1)
    report["run_files"] = sorted(p.name for p in run_dir.iterdir()) if run_dir.is_dir() else []
    if (run_dir / "physics.json").is_file():
        run = json.loads((run_dir / "physics.json").read_text())["runs"][0]
        report["simulated"] = {k: run.get(k) for k in ("material", "E", "nu")}
    report["from_venv"] = str(report["physgm_file"]).startswith(str(venv))
    report["ok"] = bool(
        report["from_venv"]
        and not report["unmet_requirements"]
        and report["wheel_materials"] == len(list((REPO / "conf" / "sim" / "material").glob("*.yaml")))
        and report["wheel_has_checkpoint"]
        and "video.mp4" in report["run_files"]
    )
    return report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python scripts/check_install.py", description=__doc__.splitlines()[0])
    p.add_argument(
        "--work", type=Path, default=None, help="empty folder to work in (default: a temporary one)"
    )
    p.add_argument("--keep", action="store_true", help="keep the work folder")
    a = p.parse_args(argv)
    work = a.work or Path(tempfile.mkdtemp(prefix="physgm-install-"))
    t0 = time.perf_counter()
    try:
        report = check_install(work)
    except RuntimeError as err:
        report = {"ok": False, "error": str(err), "work": str(work)}
    report["total_s"] = round(time.perf_counter() - t0, 1)
    if not a.keep:
        shutil.rmtree(work, ignore_errors=True)
    print(json.dumps(report, indent=1, default=str))
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
