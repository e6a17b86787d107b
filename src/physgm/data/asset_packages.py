"""robosuite and metaworld as file sources: only their asset files are read, neither is imported.

``scripts/setup.sh`` installs both with ``pip install --no-deps`` at the versions below; the
real-object set (`real_objects`) and the photographed textures (`photo_textures`) read from them.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

PINNED = {"robosuite": "1.5.2", "metaworld": "3.1.1"}  # the versions the tables were written against


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
            f"(it runs pip install --no-deps {name}=={PINNED.get(name, '...')})"
        )
    return Path(next(iter(spec.submodule_search_locations)))
