"""nerfstudio / Blender (NeRF-synthetic) ``transforms.json`` -> the project's cameras.json object.

Layout read (https://docs.nerf.studio/quickstart/data_conventions.html and the NeRF Blender
scenes):

    {"camera_model": "OPENCV",                       optional; PINHOLE / OPENCV without distortion
     "fl_x": 1111.0, "fl_y": 1111.0, "cx": 400.0, "cy": 400.0, "w": 800, "h": 800,   shared, or
     "camera_angle_x": 0.6911,                       Blender: horizontal FOV in radians
     "frames": [{"file_path": "images/frame_00001.png" | "./train/r_0",
                 "transform_matrix": [[4x4 camera-to-world, OpenGL axes]],
                 "fl_x": ..., ...}]}                 per-frame intrinsics override shared ones

The matrices are OpenGL camera-to-world (x right, y up, looking down -z); they are converted
to OpenCV. Focal lengths and principal points are in pixels (nerfstudio's cx = W / 2 for a
centred one, like the project's); from ``camera_angle_x`` f = W / (2 tan(angle / 2)) and the
principal point is the image centre. Without ``w``/``h`` the image file gives the size; a
Blender ``file_path`` without extension is a ``.png``. Lens distortion (k1..k4, p1, p2) and
non-pinhole camera models are refused: the renderer is a pinhole camera.
"""

from __future__ import annotations

import math
from pathlib import Path

from PIL import Image

from physgm.data.readers.common import GL_TO_CV, camera_frames, matrix4, number

PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
INTRINSIC_KEYS = (
    "fl_x",
    "fl_y",
    "cx",
    "cy",
    "w",
    "h",
    "camera_angle_x",
    "camera_angle_y",
    "camera_model",
    *DISTORTION_KEYS,
)


def image_file(folder: Path, file_path: str) -> str:
    """The view's path relative to ``folder`` (Blender's extension-less paths are PNGs)."""
    rel = Path(file_path)
    if not (folder / rel).is_file() and rel.suffix == "" and (folder / rel.with_suffix(".png")).is_file():
        rel = rel.with_suffix(".png")
    return rel.as_posix().removeprefix("./")


def _frame_camera(merged: dict, folder: Path, file: str, where: str, problems: list[str]) -> dict | None:
    n0 = len(problems)
    model = merged.get("camera_model")
    if model is not None and str(model).upper() not in PINHOLE_MODELS:
        problems.append(
            f"{where}: camera_model {model!r} is not a pinhole camera; undistort the images "
            f"to a pinhole model ({', '.join(PINHOLE_MODELS)}) first"
        )
    for k in DISTORTION_KEYS:
        if merged.get(k) not in (None, 0, 0.0):
            problems.append(
                f"{where}: lens distortion {k}={merged[k]!r} is not supported; undistort the "
                "images first (ns-process-data writes undistorted ones)"
            )
    w = number(merged, "w", where, problems) if "w" in merged else None
    h = number(merged, "h", where, problems) if "h" in merged else None
    if (w is None or h is None) and (folder / file).is_file():
        with Image.open(folder / file) as im:
            w, h = (float(v) for v in im.size)
    if w is None or h is None:
        problems.append(f"{where}: no image size ('w', 'h') and no readable image {file}")
    if len(problems) > n0:
        return None
    if "fl_x" in merged:
        fx = number(merged, "fl_x", where, problems)
        fy = number(merged, "fl_y", where, problems) if "fl_y" in merged else fx
    elif "camera_angle_x" in merged:
        ax = number(merged, "camera_angle_x", where, problems)
        fx = None if ax is None else 0.5 * w / math.tan(0.5 * ax)
        ay = number(merged, "camera_angle_y", where, problems) if "camera_angle_y" in merged else None
        fy = fx if ay is None else 0.5 * h / math.tan(0.5 * ay)
    else:
        problems.append(f"{where}: no focal length: give 'fl_x' (pixels) or 'camera_angle_x' (radians)")
        return None
    cx = number(merged, "cx", where, problems) if "cx" in merged else w / 2
    cy = number(merged, "cy", where, problems) if "cy" in merged else h / 2
    if len(problems) > n0:
        return None
    return {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": w, "height": h}


def translate(d: dict, folder: Path, problems: list[str]) -> dict | None:
    """The project's cameras.json object (OpenCV c2w) for a transforms.json object ``d``."""
    out, n0 = [], len(problems)
    frames = camera_frames(d, "transforms.json", problems)
    if frames is None:
        return None
    shared = {k: d[k] for k in INTRINSIC_KEYS if k in d}
    for where, fr in frames:
        c2w_gl = matrix4(fr.get("transform_matrix"), "transform_matrix", where, problems)
        file = image_file(folder, fr["file_path"])
        cam = _frame_camera(
            {**shared, **{k: fr[k] for k in INTRINSIC_KEYS if k in fr}}, folder, file, where, problems
        )
        if c2w_gl is None or cam is None:
            continue
        out.append({"file": file, "c2w": (c2w_gl @ GL_TO_CV).tolist(), **cam})
    if len(problems) > n0:
        return None
    return {"convention": "opencv", "frames": out, "converted_from": "transforms.json (OpenGL)"}
