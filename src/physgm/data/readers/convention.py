"""The ``convention`` field of the project's own cameras.json: "opencv" (the default) or "opengl"."""

from __future__ import annotations

import numpy as np

from physgm.data.readers.common import GL_TO_CV

CONVENTIONS = ("opencv", "opengl")


def to_opencv(d: dict, problems: list[str]) -> dict | None:
    """The cameras.json object with every ``c2w`` in OpenCV axes (a copy; None if the convention is unknown).

    A file without ``convention`` is OpenCV (what physgm writes). "opengl" c2w matrices (x right,
    y up, looking down -z, as Blender and nerfstudio store them) are converted; any other value
    is refused, because guessing would give wrong cameras without a warning.
    """
    convention = d.get("convention", "opencv")
    name = convention.lower() if isinstance(convention, str) else convention
    if name not in CONVENTIONS:
        problems.append(
            f"cameras.json: unknown convention {convention!r}; use 'opencv' (x right, y down, looking "
            "down +z) or 'opengl' (x right, y up, looking down -z) and give c2w in that convention"
        )
        return None
    if name == "opencv":
        return d
    frames = d.get("frames")
    if not isinstance(frames, list):
        return d  # the format check reports the missing frames
    out = []
    for fr in frames:
        if isinstance(fr, dict) and "c2w" in fr:
            try:
                c2w = np.asarray(fr["c2w"], dtype=np.float64)
            except (TypeError, ValueError):
                c2w = None
            if c2w is not None and c2w.shape == (4, 4):
                fr = {**fr, "c2w": (c2w @ GL_TO_CV).tolist()}
        out.append(fr)
    return {**d, "convention": "opencv", "frames": out, "converted_from": "opengl"}
