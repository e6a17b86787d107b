"""The PhysGM authors' release layout (PhysAssets; github.com/Hihixiaolv/PhysGM), loaded in place.

    <root>/<asset>/pose.json       {"scene_name", "frames": [{"file_path": "000.png", "w2c": 4x4,
                                    "h", "w", "fx", "fy", "cx", "cy"}, ...]}
    <root>/<asset>/000.png ...     the views, next to pose.json
    <root>/<asset>/physical.json   {"material": "Wood", "E": ..., "nu": ...}

``w2c`` is world-to-camera in OpenCV axes: their loader inverts it and reads the columns of the
inverse as right, down, forward, and in their example (cake) the camera's down axis points to
world -z, so the world is +z up like the project's. Their ``physical.json`` names materials with
capitals from a list of 14; each maps to the project's material of the same name
(``RELEASE_MATERIALS``; the choice per name and why is in docs/data.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from physgm.data.readers.common import camera_frames, matrix4
from physgm.physics.materials import MATERIAL_NAMES

# Their 14 names in their class order (MATERIAL_TO_CLASS in the release's utils.py) -> ours.
# Every name exists in the project's table, whose constitutive model differs per material where
# their simulation maps six of them (Wood, Metal, Plastic, Glass, Ceramic, Stone) to one elastoplastic
# "metal" model; the project has no reason to merge them, so the names are kept.
RELEASE_MATERIALS: dict[str, str] = {
    "Wood": "wood",
    "Metal": "metal",
    "Plastic": "plastic",
    "Glass": "glass",
    "Fabric": "fabric",
    "Leather": "leather",
    "Ceramic": "ceramic",
    "Stone": "stone",
    "Rubber": "rubber",
    "Paper": "paper",
    "Sand": "sand",
    "Snow": "snow",
    "Plasticine": "plasticine",
    "Foam": "foam",
}


def canonical_material(name: object) -> str | None:
    """The project's material for ``name``, matched without regard to case or surrounding spaces."""
    if not isinstance(name, str):
        return None
    key = name.strip().lower()
    return key if key in MATERIAL_NAMES else None


def translate_pose(d: dict, folder: Path, problems: list[str]) -> dict | None:
    """The project's cameras.json object (OpenCV c2w) for a pose.json object ``d``."""
    out, n0 = [], len(problems)
    frames = camera_frames(d, "pose.json", problems)
    if frames is None:
        return None
    for where, fr in frames:
        w2c = matrix4(fr.get("w2c"), "w2c", where, problems)
        if w2c is None:
            continue
        if abs(np.linalg.det(w2c[:3, :3])) < 1e-9:
            problems.append(f"{where}: 'w2c' is singular")
            continue
        missing = [k for k in ("fx", "fy", "cx", "cy", "w", "h") if k not in fr]
        if missing:
            problems.append(f"{where}: missing {', '.join(missing)}")
            continue
        out.append(
            {
                "file": Path(fr["file_path"]).as_posix().removeprefix("./"),
                "c2w": np.linalg.inv(w2c).tolist(),
                "fx": fr["fx"],
                "fy": fr["fy"],
                "cx": fr["cx"],
                "cy": fr["cy"],
                "width": fr["w"],
                "height": fr["h"],
            }
        )
    if len(problems) > n0:
        return None
    return {"convention": "opencv", "frames": out, "converted_from": "pose.json (w2c)"}
