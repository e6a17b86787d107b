"""Output writing: the atomic run folder, videos, the contact sheet, JSON files.

``RunFolder`` writes into a hidden temporary sibling of the run folder and renames it into place
only when everything is written, so a run folder that exists is complete; on failure the
temporary folder is removed.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import numpy as np

from physgm.errors import UserError


class RunFolder:
    """``with RunFolder(target) as tmp: ...write into tmp...`` then ``commit()``; no commit = removed."""

    def __init__(self, target: Path) -> None:
        self.target = Path(target).absolute()
        self.tmp = self.target.parent / f".{self.target.name}.tmp-{os.getpid()}"
        self.committed = False
        if self.target.exists() and (not self.target.is_dir() or any(self.target.iterdir())):
            raise UserError(
                f"output folder {self.target} already exists and is not empty; choose another "
                "paths.output_dir"
            )
        try:
            self.target.parent.mkdir(parents=True, exist_ok=True)
            shutil.rmtree(self.tmp, ignore_errors=True)
            self.tmp.mkdir()
            (self.tmp / ".write-test").write_bytes(b"")
            (self.tmp / ".write-test").unlink()
        except OSError as err:
            shutil.rmtree(self.tmp, ignore_errors=True)
            raise UserError(
                f"cannot write the run folder {self.target} ({err.strerror or err}); choose another "
                "paths.output_dir"
            ) from None

    def __enter__(self) -> Path:
        return self.tmp

    def commit(self) -> Path:
        """Move the finished outputs into place (an empty target folder, e.g. Hydra's, is replaced)."""
        if self.target.is_dir() and not any(self.target.iterdir()):
            self.target.rmdir()
        os.rename(self.tmp, self.target)
        self.committed = True
        return self.target

    def __exit__(self, exc_type, exc, tb) -> None:
        if not self.committed:
            shutil.rmtree(self.tmp, ignore_errors=True)
            # An empty run folder (made by Hydra before the run) would look like a finished empty run.
            if self.target.is_dir() and not any(self.target.iterdir()):
                self.target.rmdir()


def to_uint8(img: np.ndarray) -> np.ndarray:
    return np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def save_png(path: Path, img: np.ndarray) -> None:
    """Save float [H, W, 3] in [0, 1], uint8, or bool [H, W] (white = True) as PNG."""
    from PIL import Image

    arr = (
        (img.astype(np.uint8) * 255)
        if img.dtype == bool
        else (img if img.dtype == np.uint8 else to_uint8(img))
    )
    Image.fromarray(arr).save(path)


def write_frame_plys(trajectory, folder: Path) -> None:
    """The deformed Gaussians of every frame of a ``GaussianTrajectory`` as ``frame_0000.ply`` ...;
    the still frames after its rest frame are copies of the last one that moved."""
    from physgm.gaussians import write_ply

    folder.mkdir(parents=True, exist_ok=True)
    rest = trajectory.rest_frame
    for t in range(len(trajectory)):
        path = folder / f"frame_{t:04d}.ply"
        if rest is not None and t >= rest and t > 0:
            shutil.copyfile(folder / f"frame_{t - 1:04d}.ply", path)
        else:
            write_ply(trajectory.gaussians_at(t), path)


def write_gif(path: Path, frames: np.ndarray, fps: float) -> None:
    import imageio.v3 as iio

    iio.imwrite(path, frames, extension=".gif", duration=1000.0 / fps, loop=0)


def write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(plain_json(data), indent=2, sort_keys=False, allow_nan=False) + "\n")


def plain_json(x):
    """JSON-safe copy: numpy scalars/arrays to Python, non-finite floats to None."""
    if isinstance(x, dict):
        return {str(k): plain_json(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [plain_json(v) for v in x]
    if isinstance(x, np.ndarray):
        return plain_json(x.tolist())
    if isinstance(x, np.generic):
        return plain_json(x.item())
    if isinstance(x, Path):
        return str(x)
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def keyframe_indices(n_frames: int, count: int) -> list[int]:
    """``count`` frame indices spread evenly from the first to the last frame."""
    count = min(count, n_frames)
    return sorted({round(i * (n_frames - 1) / max(count - 1, 1)) for i in range(count)})


def contact_sheet(
    preview: np.ndarray,  # [h, w, 3] float, the input as the model saw it
    rows: list[tuple[str, np.ndarray, list[int]]],  # (label, frames [T, H, W, 3] uint8, keyframe indices)
    lines: list[str],  # text: predicted physics, what was used
    fps: float,
    tile: int = 160,
) -> np.ndarray:  # [H', W', 3] uint8
    """Input, keyframes of every run (one row each, labelled) and the physics as text."""
    from PIL import Image, ImageDraw, ImageFont

    font = ImageFont.load_default()
    label_h, pad = 14, 4
    n_key = max(len(k) for _, _, k in rows)
    text_w = 330
    row_h = tile + label_h + pad
    width = pad + (tile + pad) * (1 + n_key) + text_w
    height = max(pad + row_h * len(rows), pad + 14 * (len(lines) + 2))
    sheet = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    ph, pw = preview.shape[:2]
    scale = tile / max(ph, pw)
    pimg = Image.fromarray(to_uint8(preview)).resize(
        (max(1, round(pw * scale)), max(1, round(ph * scale))), Image.BILINEAR
    )
    sheet.paste(pimg, (pad, pad + label_h))
    draw.text((pad, pad), "input", fill=(0, 0, 0), font=font)
    for r, (label, frames, keys) in enumerate(rows):
        y = pad + r * row_h
        for j, t in enumerate(keys):
            x = pad + (tile + pad) * (1 + j)
            sheet.paste(Image.fromarray(frames[t]).resize((tile, tile), Image.BILINEAR), (x, y + label_h))
            draw.text(
                (x, y), (f"{label} " if j == 0 else "") + f"t={t / fps:.2f}s", fill=(0, 0, 0), font=font
            )
    x0 = pad + (tile + pad) * (1 + n_key)
    for i, line in enumerate(lines):
        draw.text((x0, pad + 14 * i), line, fill=(0, 0, 0), font=font)
    return np.asarray(sheet)
