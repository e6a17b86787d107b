"""Writing assets: deterministic PNG/JSON bytes and atomic asset folders.

Same inputs give the same bytes: PNGs carry no timestamp or other metadata chunk, JSON keys
are sorted. An asset is written to a hidden temporary folder and renamed when complete, so a
crash never leaves a half-written asset under its final name (and resuming skips only
finished ones).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from physgm.cameras import Cameras
from physgm.data.format import CAMERA_RADIUS, FORMAT_VERSION, FOV_DEG

TMP_PREFIX = ".tmp-"


def write_png(path: Path, rgba: np.ndarray) -> None:
    """uint8 [H, W, 4] (or [H, W, 3]) to a PNG with no metadata chunks."""
    mode = "RGBA" if rgba.shape[-1] == 4 else "RGB"
    Image.fromarray(np.ascontiguousarray(rgba), mode).save(path, format="PNG", compress_level=6)


def write_json(path: Path, obj: dict, compact: bool = False) -> None:
    """Sorted keys; ``compact`` writes one line (cameras.json: 32 matrices stay small)."""
    text = (
        json.dumps(obj, sort_keys=True, separators=(",", ":"))
        if compact
        else json.dumps(obj, indent=1, sort_keys=True)
    )
    path.write_text(text + "\n")


def to_rgba8(
    rgb_premultiplied: Tensor,  # [C, H, W, 3] composited over black
    alpha: Tensor,  # [C, H, W, 1]
) -> np.ndarray:
    """Renderer output to straight-alpha uint8 RGBA [C, H, W, 4].

    Fully transparent pixels get white colour, so viewers that ignore alpha show the white
    background the synthetic views are meant to have.
    """
    a = alpha.clamp(0, 1)
    straight = torch.where(
        a > 1e-6, rgb_premultiplied / a.clamp_min(1e-6), torch.ones_like(rgb_premultiplied)
    )
    a8 = torch.round(a * 255)
    straight = torch.where(a8 > 0, straight, torch.ones_like(straight))
    out = torch.cat([torch.round(straight.clamp(0, 1) * 255), a8], dim=-1)
    return out.to(torch.uint8).cpu().numpy()


def camera_entry(c2w: Tensor, K: Tensor, width: int, height: int) -> dict:
    """One camera as stored in cameras.json and video metadata (OpenCV c2w, pixel intrinsics)."""
    return {
        "c2w": [[round(float(x), 8) + 0.0 for x in row] for row in c2w.tolist()],  # + 0.0: no "-0.0"
        "fx": float(K[0, 0]),
        "fy": float(K[1, 1]),
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "width": int(width),
        "height": int(height),
    }


def cameras_json(
    cameras: Cameras,
    azimuths: Sequence[float] | None,
    elevations: Sequence[float] | None,
    extra: dict | None = None,
) -> dict:
    """The cameras.json object for views ``rgba/000.png ...`` in camera order."""
    frames = []
    for i in range(len(cameras)):
        entry = {
            "file": f"rgba/{i:03d}.png",
            **camera_entry(cameras.c2w[i], cameras.Ks[i], cameras.width, cameras.height),
        }
        if azimuths is not None and elevations is not None:
            entry["azimuth_deg"], entry["elevation_deg"] = float(azimuths[i]), float(elevations[i])
        frames.append(entry)
    return {"convention": "opencv", "format_version": FORMAT_VERSION, "frames": frames, **(extra or {})}


def write_views(folder: Path, rgba: np.ndarray) -> None:
    """uint8 [C, H, W, 4] to ``folder/rgba/000.png ...``."""
    (folder / "rgba").mkdir(parents=True, exist_ok=True)
    for i, img in enumerate(rgba):
        write_png(folder / "rgba" / f"{i:03d}.png", img)


def write_views_cameras_physics(
    folder: Path,
    rgba: np.ndarray,  # [C, H, W, 4] uint8
    cameras: Cameras,
    azimuths: Sequence[float],
    elevations: Sequence[float],
    physical: dict,
) -> None:
    """The files every asset has: its orbit views, ``cameras.json`` and ``physical.json``."""
    write_views(folder, rgba)
    orbit = {"radius_m": CAMERA_RADIUS, "fov_deg": FOV_DEG}
    write_json(folder / "cameras.json", cameras_json(cameras, azimuths, elevations, orbit), compact=True)
    write_json(folder / "physical.json", physical)


@contextlib.contextmanager
def atomic_asset_dir(root: Path, asset_id: str) -> Iterator[Path]:
    """Yield a temporary folder; on success it becomes ``root/asset_id`` in one rename.

    Raises FileExistsError if the asset already exists (callers skip finished assets first).
    """
    final = root / asset_id
    if final.exists():
        raise FileExistsError(f"asset {final} already exists; delete it to regenerate")
    tmp = root / f"{TMP_PREFIX}{asset_id}"
    shutil.rmtree(tmp, ignore_errors=True)  # left over from an interrupted run
    tmp.mkdir(parents=True)
    try:
        yield tmp
        os.rename(tmp, final)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
