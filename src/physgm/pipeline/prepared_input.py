"""Input stage: a photo, a folder of posed views or a 3DGS .ply -> what the model (or simulator) needs.

A single photo is framed like the training renders' single input view: the object's bounding
square spans ``TRAINING_FILL`` of the side, on white, seen by the canonical camera (elevation 0,
azimuth 0, radius ``CAMERA_RADIUS``, horizontal FOV ``FOV_DEG``; see docs/data.md). A folder is
used with its own cameras (cameras.json, docs/data.md layout), four views chosen like the
training input set when it holds more.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from physgm.cameras import Cameras, orbit_cameras
from physgm.data.format import CAMERA_RADIUS, FOV_DEG, read_cameras
from physgm.data.readers import camera_file
from physgm.errors import UserError
from physgm.gaussians import Gaussians, quat_to_rotmat, read_ply, rotmat_to_quat
from physgm.inputs import Photo, frame_object, load_photo, object_mask
from physgm.model.pretrained import CLASSIFIER_SIZE

# Median side of the object's bounding square over the side of the canonical view (view 000) in
# synthetic assets (measured on 40 assets: 10-90 % range 0.72-0.97); tests re-measure it.
TRAINING_FILL = 0.88
PREVIEW_SIZE = 256  # px, the input as shown on the contact sheet
# Rotations taking the named axis of a .ply file to +z (rows: new x, y, z).
UP_ROTATIONS = {
    "z": np.eye(3),
    "y": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
    "-y": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
}


@dataclass
class PreparedInput:
    """Model-ready views (photo, views) or Gaussians (ply), plus what the outputs show of the input."""

    kind: str  # "photo" | "views" | "ply"
    preview: np.ndarray  # [h, w, 3] float in [0, 1]
    azimuth_deg: float = 0.0  # direction of the (first) input view around the object
    elevation_deg: float = 0.0
    images: Tensor | None = None  # [V, 3, S, S] composited over white
    masks: Tensor | None = None  # [V, 1, S, S] in [0, 1]
    c2w: Tensor | None = None  # [V, 4, 4] OpenCV camera-to-world
    Ks: Tensor | None = None  # [V, 3, 3]
    classifier_images: Tensor | None = None  # [V, 3, C, C] the same framing at the ImageNet classifier's size
    gaussians: Gaussians | None = None  # ply input
    mask_image: np.ndarray | None = None  # [H, W] bool, the mask used (views side by side)
    info: dict = field(default_factory=dict)


def input_kind(path: Path) -> str:
    if not path.exists():
        raise UserError(f"input not found: {path}")
    if path.is_dir():
        return "views"
    return "ply" if path.suffix.lower() == ".ply" else "photo"


def prepare_input(path: Path, size: int | None, mask: Path | None = None, up: str = "z") -> PreparedInput:
    """Load and frame the input; ``size`` is the model's square input size (unused for .ply)."""
    kind = input_kind(path)
    if kind == "ply":
        if mask is not None:
            raise UserError("mask= applies to a photo input, not to a .ply")
        return _prepare_ply(path, up)
    assert size is not None
    if kind == "views":
        if mask is not None:
            raise UserError(
                "mask= applies to a single photo; a views folder takes its masks from alpha or segmentation"
            )
        return _prepare_views(path, size)
    return _prepare_photo(path, size, mask)


def _photo_and_mask(path: Path, mask: Path | None) -> tuple[Photo, np.ndarray, str]:
    try:
        photo = load_photo(path)
        obj, source = object_mask(photo, mask)
    except FileNotFoundError as err:
        raise UserError(str(err)) from None
    except ValueError as err:
        raise UserError(str(err)) from None
    return photo, obj, source


def _prepare_photo(path: Path, size: int, mask: Path | None) -> PreparedInput:
    photo, obj, source = _photo_and_mask(path, mask)
    # Soft alpha like the training views (their RGBA over white); segmentation masks are hard.
    soft = photo.alpha if source == "alpha" else None
    rgb, m = frame_object(photo.rgb, obj, size, TRAINING_FILL, soft)
    if not (m > 0.5).any():
        raise UserError(
            f"the object in {path} vanished when framed at {size} px; give a larger or tighter photo"
        )
    preview, _ = frame_object(photo.rgb, obj, PREVIEW_SIZE, TRAINING_FILL, soft)
    classifier_view, _ = frame_object(photo.rgb, obj, CLASSIFIER_SIZE, TRAINING_FILL, soft)
    cams = orbit_cameras([0.0], [0.0], CAMERA_RADIUS, FOV_DEG, size, size)
    return PreparedInput(
        kind="photo",
        preview=preview,
        images=torch.from_numpy(rgb).permute(2, 0, 1)[None].float(),
        masks=torch.from_numpy(m)[None, None],
        c2w=cams.c2w,
        Ks=cams.Ks,
        classifier_images=torch.from_numpy(classifier_view).permute(2, 0, 1)[None].float(),
        mask_image=obj,
        info={
            "path": str(path),
            "size": list(photo.rgb.shape[1::-1]),
            "mask_source": source,
            "mask_fraction": round(float(obj.mean()), 4),
            "views": 1,
            "fill": TRAINING_FILL,
        },
    )


def _read_cameras(folder: Path) -> tuple[list[Path], Cameras]:
    """The folder's views and cameras: cameras.json, or a transforms.json / pose.json (docs/interop.md)."""
    if camera_file(folder) is None:
        raise UserError(
            f"{folder} is a folder but has no cameras.json (nor transforms.json or pose.json); "
            "give a photo, a .ply, or 4 posed views (docs/data.md)"
        )
    problems: list[str] = []
    parsed = read_cameras(folder, problems)
    if problems or parsed is None:
        raise UserError(
            f"{camera_file(folder)}: "
            + "; ".join(problems[:3])
            + (f" (+{len(problems) - 3} more)" if len(problems) > 3 else "")
        )
    cams, files, _, _ = parsed
    return files, cams


def _square(rgb: np.ndarray, mask: np.ndarray, K: Tensor, size: int) -> tuple[Tensor, Tensor, Tensor]:
    """Centre-crop to a square and resize to ``size``; intrinsics follow. Returns [3,S,S], [1,S,S], [3,3]."""
    import cv2

    h, w = mask.shape
    side = min(h, w)
    y0, x0 = (h - side) // 2, (w - side) // 2
    alpha = mask[y0 : y0 + side, x0 : x0 + side].astype(np.float32)
    comp = rgb[y0 : y0 + side, x0 : x0 + side] * alpha[..., None] + (1 - alpha[..., None])  # over white
    K = K.clone()
    K[0, 2] -= x0
    K[1, 2] -= y0
    K[:2] *= size / side
    comp = cv2.resize(comp, (size, size), interpolation=cv2.INTER_AREA)
    alpha = cv2.resize(alpha, (size, size), interpolation=cv2.INTER_AREA)
    return (
        torch.from_numpy(np.clip(comp, 0, 1)).permute(2, 0, 1),
        torch.from_numpy(np.clip(alpha, 0, 1))[None],
        K,
    )


def _prepare_views(folder: Path, size: int) -> PreparedInput:
    from physgm.data.views import ViewConfig, select_views

    files, cams = _read_cameras(folder)
    if len(files) < 4 and len(files) != 1:
        raise UserError(
            f"{folder} has {len(files)} views; the model takes 1 or 4 posed views (give 4, or a single photo)"
        )
    chosen = (
        list(range(len(files)))
        if len(files) in (1, 4)
        else select_views(cams.c2w, ViewConfig(num_targets=4), None)[0]
    )
    images, masks, Ks, mask_images, sources, classifier_images = [], [], [], [], [], []
    for i in chosen:
        photo, obj, source = _photo_and_mask(files[i], None)
        if photo.rgb.shape[:2] != (cams.height, cams.width):
            raise UserError(
                f"{files[i]} is {photo.rgb.shape[1]} x {photo.rgb.shape[0]} px but cameras.json says "
                f"{cams.width} x {cams.height}"
            )
        # Keep soft alpha edges like the training views; segmentation masks are hard.
        soft = photo.alpha if source == "alpha" else obj.astype(np.float32)
        img, m, K = _square(photo.rgb, soft, cams.Ks[i], size)
        images.append(img), masks.append(m), Ks.append(K), mask_images.append(obj), sources.append(source)
        classifier_images.append(_square(photo.rgb, soft, cams.Ks[i], CLASSIFIER_SIZE)[0])
    centre = cams.c2w[chosen[0], :3, 3].double()
    azimuth = math.degrees(math.atan2(float(centre[1]), float(centre[0])))
    elevation = math.degrees(math.asin(max(-1.0, min(1.0, float(centre[2] / centre.norm().clamp_min(1e-9))))))
    preview = np.concatenate([im.permute(1, 2, 0).numpy() for im in images], axis=1)
    return PreparedInput(
        kind="views",
        preview=preview,
        azimuth_deg=azimuth,
        elevation_deg=elevation,
        images=torch.stack(images).float(),
        masks=torch.stack(masks).float(),
        c2w=cams.c2w[chosen],
        Ks=torch.stack(Ks),
        classifier_images=torch.stack(classifier_images).float(),
        mask_image=np.concatenate(mask_images, axis=1)
        if len({m.shape for m in mask_images}) == 1
        else mask_images[0],
        info={
            "path": str(folder),
            "views": len(chosen),
            "files": [files[i].name for i in chosen],
            "mask_source": sorted(set(sources)),
            "size": [cams.width, cams.height],
        },
    )


def rotate_gaussians(g: Gaussians, rot: np.ndarray) -> Gaussians:
    """Gaussians rotated about the origin by ``rot`` [3, 3] (positions and orientations)."""
    r = torch.from_numpy(rot).to(g.means)
    quats = rotmat_to_quat(r @ quat_to_rotmat(g.quats))
    return Gaussians(g.means @ r.T, quats, g.scales, g.opacities, g.colors)


def _prepare_ply(path: Path, up: str) -> PreparedInput:
    import warnings

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # higher SH degrees are dropped on purpose: we render degree 0
            g = read_ply(path, keep_sh=False)
    except (FileNotFoundError, ValueError) as err:
        raise UserError(str(err)) from None
    if len(g) == 0:
        raise UserError(f"{path} holds no Gaussians")
    # Other tools' SH DC colours can leave [0, 1]; the renderer and the simulator expect RGB in it.
    g = Gaussians(
        g.means.float(), g.quats.float(), g.scales.float(), g.opacities.float(), g.colors.float().clamp(0, 1)
    )
    g = rotate_gaussians(g, UP_ROTATIONS[up])
    return PreparedInput(
        kind="ply",
        preview=np.ones((PREVIEW_SIZE, PREVIEW_SIZE, 3), np.float32),
        gaussians=g,
        info={"path": str(path), "gaussians": len(g), "up": up},
    )
