"""The PhysAssets on-disk format: one folder per asset (see docs/data.md).

    <root>/<asset_id>/rgba/000.png ...   RGBA views, straight (not premultiplied) alpha
    <root>/<asset_id>/cameras.json       per view: OpenCV c2w 4x4, fx fy cx cy, width, height
    <root>/<asset_id>/physical.json      material, E (Pa), nu, density, constitutive_model, annotation
    <root>/<asset_id>/gaussians.ply      ground-truth Gaussians (synthetic assets), 3DGS layout
    <root>/<asset_id>/videos/<scene>.mp4 + <scene>.json   optional reference videos
    <root>/splits/{train,val,test,dpo}.txt                asset ids, one per line

``read_asset`` parses an asset and collects every problem it finds; ``load_asset`` raises
``AssetError`` listing them. Pixel-level checks (decoding every PNG) live in ``check.py``.
Folders laid out by other tools (nerfstudio/Blender ``transforms.json``, the PhysGM authors'
``pose.json`` and capitalised material names) load in place through ``physgm.data.readers``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from physgm.cameras import Cameras
from physgm.data.annotation import E_CATEGORIES, NU_CATEGORIES, e_class, nu_class
from physgm.data.priors import material_names
from physgm.data.readers import read_camera_dict
from physgm.data.readers.common import load_json as _load_json
from physgm.data.readers.common import number as _number
from physgm.data.readers.physgm_release import canonical_material

# The synthetic view grid: 4 elevations x 8 azimuths, elevation-major (view = 8 * e + a).
VIEW_ELEVATIONS_DEG: tuple[float, ...] = (0.0, 20.0, 40.0, 60.0)
VIEW_AZIMUTHS_DEG: tuple[float, ...] = tuple(45.0 * i for i in range(8))
CAMERA_RADIUS = 1.8  # m
# Horizontal FOV: the object's bounding sphere (radius 0.5) seen from 1.8 m subtends
# 2 asin(0.5 / 1.8) = 32.3 degrees, so 34 degrees fills the frame with a thin margin.
FOV_DEG = 34.0
SPLITS = ("train", "val", "test", "dpo")
SPLITS_DIR = "splits"
FORMAT_VERSION = 1


class AssetError(ValueError):
    """A malformed asset; the message lists every problem found."""


@dataclass
class Annotated:
    """Coarse labels from the annotator (classes index E_CATEGORIES / NU_CATEGORIES)."""

    material: str
    E: float  # Pa, one of E_CATEGORIES
    nu: float  # one of NU_CATEGORIES
    E_class: int
    nu_class: int


@dataclass
class PhysicalLabels:
    """Contents of physical.json.

    ``material``/``E``/``nu`` are the true values for synthetic assets. Real assets (the PhysGM
    release) carry only annotated values there; then ``true_known`` is False and ``annotation``
    is built from the same fields.
    """

    material: str
    E: float  # Pa
    nu: float
    density: float | None  # kg/m^3
    constitutive_model: str | None
    annotation: Annotated
    true_known: bool
    extra: dict = field(default_factory=dict)  # every other key, kept verbatim


@dataclass
class VideoInfo:
    """A reference video: ``videos/<scene>.mp4`` and its metadata ``videos/<scene>.json``."""

    scene: str
    path: Path
    fps: float
    frames: int
    cameras: Cameras  # one camera


@dataclass
class Asset:
    """One asset folder, parsed. Images are read on demand with ``load_rgba``."""

    id: str
    path: Path
    cameras: Cameras  # C views
    view_files: list[Path]  # [C]
    azimuth_deg: np.ndarray | None  # [C] where known
    elevation_deg: np.ndarray | None  # [C]
    physical: PhysicalLabels
    videos: list[VideoInfo]
    gaussians_path: Path | None

    def __len__(self) -> int:
        return len(self.view_files)

    def load_rgba(self, indices: list[int] | None = None) -> np.ndarray:
        """Views as float32 [V, H, W, 4] in [0, 1], straight alpha."""
        indices = range(len(self)) if indices is None else indices
        return np.stack([read_rgba(self.view_files[i]) for i in indices]).astype(np.float32) / 255.0

    def load_gaussians(self, keep_sh: bool = True):
        from physgm.gaussians import read_ply

        if self.gaussians_path is None:
            raise FileNotFoundError(f"asset {self.id} has no gaussians.ply")
        return read_ply(self.gaussians_path, keep_sh=keep_sh)


def read_rgba(path: Path | str) -> np.ndarray:
    """A PNG as uint8 [H, W, 4]; RGB files get an opaque alpha channel."""
    with Image.open(path) as im:
        return np.asarray(im.convert("RGBA"))


def view_grid() -> tuple[list[float], list[float]]:
    """Azimuths and elevations (degrees) of the 32 synthetic views, in file order."""
    az = [a for _ in VIEW_ELEVATIONS_DEG for a in VIEW_AZIMUTHS_DEG]
    el = [e for e in VIEW_ELEVATIONS_DEG for _ in VIEW_AZIMUTHS_DEG]
    return az, el


# ---------------------------------------------------------------------------------------------
# Parsing with problem collection.


def parse_camera(d: dict, where: str, problems: list[str]) -> tuple[np.ndarray, np.ndarray, int, int] | None:
    """One camera entry -> (c2w [4, 4], K [3, 3], width, height), or None with problems noted."""
    n0 = len(problems)
    try:
        c2w = np.asarray(d.get("c2w"), dtype=np.float64)
    except (TypeError, ValueError):
        problems.append(f"{where}: c2w is not a 4x4 array of numbers")
        return None
    if c2w.shape != (4, 4):
        problems.append(f"{where}: c2w must be 4x4, got shape {c2w.shape}")
        return None
    if not np.isfinite(c2w).all():
        problems.append(f"{where}: c2w has non-finite entries")
        return None
    rot = c2w[:3, :3]
    if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(rot) - 1) > 1e-3:
        problems.append(f"{where}: c2w rotation is not orthonormal with det +1")
    if np.abs(c2w[3] - [0, 0, 0, 1]).max() > 1e-6:
        problems.append(f"{where}: last row of c2w must be [0, 0, 0, 1]")
    vals = {k: _number(d, k, where, problems) for k in ("fx", "fy", "cx", "cy", "width", "height")}
    if len(problems) > n0:
        return None
    if vals["fx"] <= 0 or vals["fy"] <= 0:
        problems.append(f"{where}: focal lengths must be positive, got fx={vals['fx']} fy={vals['fy']}")
    w, h = vals["width"], vals["height"]
    if w != int(w) or h != int(h) or w <= 0 or h <= 0:
        problems.append(f"{where}: width and height must be positive integers, got {w} x {h}")
    if len(problems) > n0:
        return None
    K = np.array([[vals["fx"], 0, vals["cx"]], [0, vals["fy"], vals["cy"]], [0, 0, 1]])
    return c2w, K, int(w), int(h)


def parse_physical(d: dict, problems: list[str]) -> PhysicalLabels | None:
    n0 = len(problems)
    names = material_names()
    written = d.get("material")
    material = canonical_material(written)  # "Wood" (the PhysGM release) is wood
    if material is None:
        problems.append(f"physical.json: unknown material {written!r} (known, any case: {', '.join(names)})")
    E = _number(d, "E", "physical.json", problems)
    nu = _number(d, "nu", "physical.json", problems)
    if E is not None and E <= 0:
        problems.append(f"physical.json: E must be positive (Pa), got {E}")
    if nu is not None and not -1.0 < nu < 0.5:
        problems.append(f"physical.json: nu must be in (-1, 0.5) for a stable solid, got {nu}")
    density = None
    if d.get("density") is not None:
        density = _number(d, "density", "physical.json", problems)
        if density is not None and density <= 0:
            problems.append(f"physical.json: density must be positive (kg/m^3), got {density}")
    ann = d.get("annotation")
    annotated = None
    if isinstance(ann, dict):
        a_mat = canonical_material(ann.get("material"))
        if a_mat is None:
            problems.append(f"physical.json: annotation has unknown material {ann.get('material')!r}")
        a_E = _number(ann, "E", "physical.json annotation", problems)
        a_nu = _number(ann, "nu", "physical.json annotation", problems)
        if a_E is not None and a_E not in E_CATEGORIES:
            problems.append(f"physical.json: annotation E {a_E} is not one of the categories {E_CATEGORIES}")
        if a_nu is not None and a_nu not in NU_CATEGORIES:
            problems.append(
                f"physical.json: annotation nu {a_nu} is not one of the categories {NU_CATEGORIES}"
            )
        if len(problems) == n0:
            annotated = Annotated(a_mat, a_E, a_nu, E_CATEGORIES.index(a_E), NU_CATEGORIES.index(a_nu))
    elif ann is not None:
        problems.append("physical.json: 'annotation' must be an object with material, E, nu")
    if len(problems) > n0:
        return None
    true_known = annotated is not None
    if annotated is None:  # real asset: the stored labels are the annotation
        ec, nc = int(e_class(E)), int(nu_class(nu))
        annotated = Annotated(material, E_CATEGORIES[ec], NU_CATEGORIES[nc], ec, nc)
    known = {"material", "E", "nu", "density", "constitutive_model", "annotation"}
    extra = {k: v for k, v in d.items() if k not in known}
    if written != material:
        extra["material_as_written"] = written
    return PhysicalLabels(
        material,
        E,
        nu,
        density,
        d.get("constitutive_model"),
        annotated,
        true_known,
        extra,
    )


def _parse_cameras(d: dict, path: Path, problems: list[str]):
    frames = d.get("frames")
    if not isinstance(frames, list) or not frames:
        problems.append("cameras.json: 'frames' must be a non-empty list")
        return None
    c2ws, Ks, files, az, el, sizes = [], [], [], [], [], set()
    for i, fr in enumerate(frames):
        where = f"cameras.json frame {i}"
        if not isinstance(fr, dict):
            problems.append(f"{where}: must be an object")
            continue
        cam = parse_camera(fr, where, problems)
        name = fr.get("file")
        if not isinstance(name, str):
            problems.append(f"{where}: 'file' must name the view image")
        elif not (path / name).is_file():
            problems.append(f"{where}: view image {name} is missing")
        if cam is None or not isinstance(name, str):
            continue
        c2ws.append(cam[0]), Ks.append(cam[1]), files.append(path / name), sizes.add(cam[2:])
        az.append(fr.get("azimuth_deg")), el.append(fr.get("elevation_deg"))
    if len(sizes) > 1:
        problems.append(f"cameras.json: all views must share one image size, got {sorted(sizes)}")
    if len(c2ws) != len(frames) or len(sizes) != 1:
        return None
    ((w, h),) = sizes
    cams = Cameras(
        torch.tensor(np.stack(c2ws), dtype=torch.float32),
        torch.tensor(np.stack(Ks), dtype=torch.float32),
        w,
        h,
    )
    known = all(
        isinstance(a, (int, float)) and isinstance(e, (int, float)) for a, e in zip(az, el, strict=True)
    )
    return cams, files, (np.asarray(az, float) if known else None), (np.asarray(el, float) if known else None)


def read_cameras(path: Path, problems: list[str]):
    """The views of a folder: (Cameras, view files, azimuths, elevations), or None with problems noted.

    Reads cameras.json, or a nerfstudio/Blender transforms.json or a PhysGM pose.json in its place.
    """
    cam_json = read_camera_dict(Path(path), problems)
    return _parse_cameras(cam_json, Path(path), problems) if cam_json is not None else None


def _parse_videos(path: Path, problems: list[str]) -> list[VideoInfo]:
    out = []
    vdir = path / "videos"
    if not vdir.is_dir():
        return out
    for meta_path in sorted(vdir.glob("*.json")):
        where = f"videos/{meta_path.name}"
        meta = _load_json(meta_path, problems)
        mp4 = meta_path.with_suffix(".mp4")
        if not mp4.is_file():
            problems.append(f"{where}: video file videos/{mp4.name} is missing")
        if meta is None:
            continue
        n0 = len(problems)
        fps = _number(meta, "fps", where, problems)
        frames = _number(meta, "frames", where, problems)
        cam = parse_camera(
            meta.get("camera", {}) if isinstance(meta.get("camera"), dict) else {},
            f"{where} camera",
            problems,
        )
        if fps is not None and fps <= 0:
            problems.append(f"{where}: fps must be positive, got {fps}")
        if len(problems) > n0 or not mp4.is_file():
            continue
        c2w, K, w, h = cam
        cams = Cameras(
            torch.tensor(c2w[None], dtype=torch.float32), torch.tensor(K[None], dtype=torch.float32), w, h
        )
        out.append(VideoInfo(meta_path.stem, mp4, fps, int(frames), cams))
    for mp4 in sorted(vdir.glob("*.mp4")):
        if not mp4.with_suffix(".json").is_file():
            problems.append(f"videos/{mp4.name} has no metadata file videos/{mp4.stem}.json")
    return out


def read_asset(path: str | os.PathLike) -> tuple[Asset | None, list[str]]:
    """Parse an asset folder, collecting every structural problem instead of stopping."""
    path = Path(path)
    problems: list[str] = []
    if not path.is_dir():
        return None, [f"{path} is not a directory"]
    cams = read_cameras(path, problems)
    phys_json = _load_json(path / "physical.json", problems)
    physical = parse_physical(phys_json, problems) if phys_json is not None else None
    videos = _parse_videos(path, problems)
    ply = path / "gaussians.ply"
    if problems or cams is None or physical is None:
        return None, problems
    cameras, files, az, el = cams
    return Asset(
        path.name, path, cameras, files, az, el, physical, videos, ply if ply.is_file() else None
    ), []


def load_asset(path: str | os.PathLike) -> Asset:
    """Parse an asset folder or raise ``AssetError`` naming the asset and every problem."""
    asset, problems = read_asset(path)
    if problems:
        listing = "\n  - ".join(problems)
        raise AssetError(
            f"asset {path} is malformed:\n  - {listing}\nFix or remove it; `python -m physgm.data.check "
            f"{Path(path).parent}` lists every defect in the data set."
        )
    return asset


def evenly_spaced(ids: list[str], count: int | None) -> list[str]:
    """At most ``count`` of ``ids``, spread evenly over the list (all of them for None)."""
    if count is not None and count < 1:
        raise ValueError(f"a subset needs at least 1 asset, got {count}")
    if count is None or count >= len(ids):
        return list(ids)
    return [ids[i * len(ids) // count] for i in range(count)]


def read_split(root: str | os.PathLike, split: str) -> list[str]:
    """Asset ids of one split (``splits/<split>.txt``, one id per line, '#' comments allowed)."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; choose one of {SPLITS}")
    path = Path(root) / SPLITS_DIR / f"{split}.txt"
    if not path.is_file():
        raise FileNotFoundError(f"no split file {path}; generate the data set first or write the split list")
    ids = [ln.split("#")[0].strip() for ln in path.read_text().splitlines()]
    return [i for i in ids if i]
