"""Files that ship inside the package: the config tree and the tiny checkpoint.

In the checkout, ``src/physgm/conf`` and ``src/physgm/checkpoints`` are symlinks to the
repository's ``conf/`` and ``checkpoints/`` (one copy, edited where the configs live); the wheel
holds real copies (``[tool.setuptools.package-data]`` in pyproject.toml). Everything is found
through ``importlib.resources``, so an installed package run from any folder reads the same
material table, scenes and solver settings as the checkout.
"""

from __future__ import annotations

from importlib.resources import files
from importlib.resources.abc import Traversable
from pathlib import Path

PACKAGE = "physgm"


def package_file(*parts: str) -> Traversable:
    """A file or folder inside the installed package, e.g. ``package_file("conf", "sim")``."""
    return files(PACKAGE).joinpath(*parts)


def conf_dir() -> Path:
    """The config tree (``conf/``) as a folder on disk, for Hydra.

    Hydra needs a real directory; wheels are always unpacked by pip, so the package's files are.
    """
    conf = package_file("conf")
    if not isinstance(conf, Path) or not conf.is_dir():
        raise FileNotFoundError(
            f"the physgm config tree is missing at {conf}; reinstall the package "
            "(`pip install .`), or in a checkout restore the symlink src/physgm/conf -> ../../conf"
        )
    return conf


def packaged_checkpoint(relative: str | Path) -> Path | None:
    """The copy of ``checkpoints/<name>`` shipped with the package, if there is one."""
    rel = Path(relative)
    if rel.is_absolute() or not rel.parts or rel.parts[0] != "checkpoints":
        return None
    path = package_file(*rel.parts)
    return path if isinstance(path, Path) and path.is_file() else None
