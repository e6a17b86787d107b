"""Readers: other tools' files translated into the project's own format (docs/data.md, docs/interop.md).

Camera files are translated into the project's cameras.json object (OpenCV camera-to-world,
pixel intrinsics, one entry per view), which ``physgm.data.format`` then checks exactly like a
native file, so a foreign asset folder loads in place (training, ``physgm.data.check``, shards,
``simulate.py input=FOLDER``). An asset folder holds one of, in this order of preference:

    cameras.json     the project's own, honouring its ``convention`` (convention.py)
    transforms.json  nerfstudio / Blender (nerfstudio.py)
    pose.json        the PhysGM authors' release (physgm_release.py)

``physgaussian.py`` reads PhysGaussian's simulation config for ``simulate.py``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from physgm.data.readers import convention, nerfstudio, physgm_release
from physgm.data.readers.common import load_json

CameraTranslator = Callable[[dict, Path, list[str]], dict | None]
CAMERA_FILES: dict[str, CameraTranslator] = {
    "cameras.json": lambda d, folder, problems: convention.to_opencv(d, problems),
    "transforms.json": nerfstudio.translate,
    "pose.json": physgm_release.translate_pose,
}


def camera_file(folder: Path) -> Path | None:
    """The camera file of an asset or views folder (the first of ``CAMERA_FILES`` present)."""
    for name in CAMERA_FILES:
        if (folder / name).is_file():
            return folder / name
    return None


def read_camera_dict(folder: Path, problems: list[str]) -> dict | None:
    """The folder's cameras as the project's cameras.json object, or None with the problems noted."""
    path = camera_file(folder)
    if path is None:
        problems.append("missing cameras.json (or a transforms.json or pose.json to read cameras from)")
        return None
    d = load_json(path, problems)
    return None if d is None else CAMERA_FILES[path.name](d, folder, problems)
