"""JSON helpers shared by the project's format and the readers: every problem is collected, not raised."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

# Right-multiplying an OpenGL/Blender camera-to-world (x right, y up, looking down -z) by this
# gives the OpenCV one (x right, y down, looking down +z): the camera's y and z axes flip.
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def load_json(path: Path, problems: list[str]) -> dict | None:
    """A JSON object from ``path``, or None with the reason appended to ``problems``."""
    if not path.is_file():
        problems.append(f"missing {path.name}")
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        problems.append(f"{path.name} is not valid JSON ({err})")
        return None
    if not isinstance(data, dict):
        problems.append(f"{path.name} must hold a JSON object, got {type(data).__name__}")
        return None
    return data


def camera_frames(d: dict, source: str, problems: list[str]) -> list[tuple[str, dict]] | None:
    """The frames of a camera file's object ``d`` (``source``: its name, e.g. "pose.json") that are
    objects with a 'file_path', each as (where, frame) with its place for messages; the others
    are noted in ``problems``. None when ``d`` has no non-empty 'frames' list."""
    frames = d.get("frames")
    if not isinstance(frames, list) or not frames:
        problems.append(f"{source}: 'frames' must be a non-empty list")
        return None
    usable = []
    for i, fr in enumerate(frames):
        where = f"{source} frame {i}"
        if not isinstance(fr, dict) or not isinstance(fr.get("file_path"), str):
            problems.append(f"{where}: must be an object with a 'file_path'")
            continue
        usable.append((where, fr))
    return usable


def number(d: dict, key: str, where: str, problems: list[str]) -> float | None:
    """``d[key]`` as a finite float (numeric strings accepted), or None with a problem noted."""
    value = d.get(key)
    try:
        out = float(value)
    except (TypeError, ValueError):
        problems.append(f"{where}: '{key}' must be a number, got {value!r}")
        return None
    if not math.isfinite(out):
        problems.append(f"{where}: '{key}' is not finite ({value!r})")
        return None
    return out


def matrix4(value, key: str, where: str, problems: list[str]) -> np.ndarray | None:
    """A finite 4x4 matrix (a 3x4 one gets the row [0, 0, 0, 1]), or None with a problem noted."""
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        problems.append(f"{where}: '{key}' is not a 4x4 array of numbers")
        return None
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4) or not np.isfinite(m).all():
        problems.append(f"{where}: '{key}' must be a finite 4x4 matrix, got shape {m.shape}")
        return None
    return m
