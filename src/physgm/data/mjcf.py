"""Visual triangles of a MuJoCo (MJCF) body, coloured like its materials, for the ray caster.

Robot-learning packages (metaworld, robosuite) describe objects as MJCF bodies: STL parts and
primitive geoms placed by body and geom ``pos``/``quat``/``euler``/``axisangle``/``fromto``,
with per-geom materials (an ``rgba``, or a cube texture). ``assemble`` walks one body and
returns each visible geom as a ``Part``: triangles in the body's frame (metres) and a
``physgm.data.from_meshes.ColourSource``.

What MuJoCo's renderer does that this does not: specular light and reflections, and
transparency (a translucent material is drawn opaque, in the colour it shows over a light
background, because the ray caster keeps only the first hit). Cube textures are box-projected
per face, the image once across the geom's longest side times ``texrepeat``, which is close to
MuJoCo's cube mapping of meshes without texture coordinates but not the same.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from physgm.data.from_meshes import ColourSource

HIDDEN_GROUPS = {3, 4, 5}  # MuJoCo's collision / helper geom groups, not rendered by default
SEEN_THROUGH = 0.85  # grey a translucent part is blended towards (what shows through it)
DEFAULT_RGBA = (0.5, 0.5, 0.5, 1.0)  # MuJoCo's default geom colour


@dataclass
class Part:
    """One visible geom."""

    triangles: np.ndarray  # [M, 3, 3] in the assembled body's frame, m
    colour: ColourSource
    name: str  # mesh name or geom type, for messages


@dataclass
class Assets:
    """What MJCF files declare: meshes, textures, materials, default classes."""

    meshes: dict[str, tuple[Path, np.ndarray]] = field(default_factory=dict)  # name -> (file, scale [3])
    textures: dict[str, Path] = field(default_factory=dict)
    materials: dict[str, dict[str, str]] = field(default_factory=dict)
    defaults: dict[str, dict[str, str]] = field(default_factory=dict)  # class -> geom attributes
    degrees: bool = False  # compiler angle; both packages write radians


def _floats(text: str | None, default: tuple[float, ...] = ()) -> np.ndarray:
    return np.array([float(v) for v in text.split()] if text else default, dtype=np.float64)


def _resolve(ref: str, search: list[Path]) -> Path:
    for base in search:
        path = (base / ref).resolve()
        if path.is_file():
            return path
    raise FileNotFoundError(f"MJCF file reference {ref!r} not found under any of {[str(s) for s in search]}")


def read_assets(files: list[Path], search: list[Path]) -> Assets:
    """Meshes, textures, materials and default classes declared in ``files``.

    File references are resolved against each folder of ``search`` in turn (MuJoCo resolves them
    against the top-level model's folder, which for included files is not their own).
    """
    out = Assets()
    for path in files:
        root = ET.parse(path).getroot()
        for comp in root.iter("compiler"):
            if comp.get("angle"):
                out.degrees = comp.get("angle") == "degree"
        for mesh in root.iter("mesh"):
            file = mesh.get("file")
            if file:
                name = mesh.get("name") or Path(file).stem
                out.meshes[name] = (_resolve(file, search), _floats(mesh.get("scale"), (1, 1, 1)))
        for tex in root.iter("texture"):
            if tex.get("file") and tex.get("name"):
                out.textures[tex.get("name")] = _resolve(tex.get("file"), search)
        for mat in root.iter("material"):
            out.materials[mat.get("name")] = dict(mat.attrib)
        for top in root.findall("default"):
            _read_defaults(top, {}, out.defaults)
    return out


def _read_defaults(node: ET.Element, inherited: dict[str, str], table: dict[str, dict[str, str]]) -> None:
    geom = node.find("geom")
    attrs = {**inherited, **(geom.attrib if geom is not None else {})}
    table[node.get("class", "main")] = attrs
    for child in node.findall("default"):
        _read_defaults(child, attrs, table)


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    x, y, z = axis
    k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def frame(attrs: dict[str, str], degrees: bool = False) -> np.ndarray:
    """The 4x4 child-to-parent transform of a body or geom element's attributes."""
    scale = np.pi / 180 if degrees else 1.0
    T = np.eye(4)
    T[:3, 3] = _floats(attrs.get("pos"), (0, 0, 0))
    if "quat" in attrs:
        T[:3, :3] = _quat_matrix(_floats(attrs["quat"]))
    elif "euler" in attrs:  # MuJoCo's default eulerseq "xyz": intrinsic, so R = Rx Ry Rz
        a = _floats(attrs["euler"]) * scale
        T[:3, :3] = _axis_rotation(np.eye(3)[0], a[0]) @ _axis_rotation(np.eye(3)[1], a[1])
        T[:3, :3] = T[:3, :3] @ _axis_rotation(np.eye(3)[2], a[2])
    elif "axisangle" in attrs:
        aa = _floats(attrs["axisangle"])
        T[:3, :3] = _axis_rotation(aa[:3], aa[3] * scale)
    elif "xyaxes" in attrs or "zaxis" in attrs:
        raise ValueError(f"MJCF orientation {attrs} uses xyaxes/zaxis, which physgm.data.mjcf does not read")
    return T


def _primitive(kind: str, size: np.ndarray, fromto: np.ndarray | None) -> tuple[trimesh.Trimesh, np.ndarray]:
    """A primitive geom's mesh in its own frame, and the extra transform ``fromto`` implies."""
    extra = np.eye(4)
    if fromto is not None:  # a segment from a to b replaces pos/orientation and the half-length
        a, b = fromto[:3], fromto[3:]
        axis = b - a
        half = np.linalg.norm(axis) / 2
        size = np.array([size[0], half])
        z = np.array([0.0, 0.0, 1.0])
        cross = np.cross(z, axis / (2 * half))
        angle = np.arctan2(np.linalg.norm(cross), axis[2] / (2 * half))
        if np.linalg.norm(cross) > 1e-12:
            extra[:3, :3] = _axis_rotation(cross, angle)
        elif axis[2] < 0:
            extra[:3, :3] = np.diag([1.0, -1.0, -1.0])
        extra[:3, 3] = (a + b) / 2
    if kind == "box":
        return trimesh.creation.box(extents=2 * size[:3]), extra
    if kind == "sphere":
        return trimesh.creation.icosphere(subdivisions=3, radius=size[0]), extra
    if kind == "ellipsoid":
        m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        m.apply_scale(size[:3])
        return m, extra
    if kind == "cylinder":
        return trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=32), extra
    if kind == "capsule":
        return trimesh.creation.capsule(height=2 * size[1], radius=size[0], count=[24, 24]), extra
    raise ValueError(
        f"MJCF geom type {kind!r} is not supported (mesh, box, sphere, ellipsoid, cylinder, capsule)"
    )


def box_projected(
    triangles: np.ndarray, image: np.ndarray, repeat: np.ndarray, factor: np.ndarray
) -> ColourSource:
    """A texture laid on each face along its dominant normal axis (no texture coordinates needed).

    triangles: [M, 3, 3] m; image: [H, W, 3] in [0, 1]; repeat: [2]; factor: [3] colour multiplier.
    """
    normal = np.abs(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]))
    dominant = normal.argmax(1)  # [M]
    plane = np.array([[1, 2], [0, 2], [0, 1]])[dominant]  # [M, 2] the two axes the face spans
    lo = triangles.reshape(-1, 3).min(0)
    extent = max(float(np.ptp(triangles.reshape(-1, 3), axis=0).max()), 1e-9)
    coords = (triangles - lo) / extent  # [M, 3, 3] in [0, 1] along the longest side
    uv = np.take_along_axis(coords, np.repeat(plane[:, None, :], 3, axis=1), axis=2) * repeat
    faces = np.arange(3 * len(triangles)).reshape(-1, 3)
    return ColourSource(faces, uv=uv.reshape(-1, 2), image=image, factor=factor)


def load_image(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"), dtype=np.float64) / 255.0


def _colour(attrs: dict[str, str], assets: Assets, triangles: np.ndarray) -> ColourSource | None:
    """The geom's colour source, or None for an invisible geom."""
    material = assets.materials.get(attrs.get("material", ""))
    if material is not None:  # a material's colour wins over the geom's; its own default is white
        rgba = _floats(material.get("rgba"), (1.0, 1.0, 1.0, 1.0))
    else:
        material, rgba = {}, _floats(attrs.get("rgba"), DEFAULT_RGBA)
    if rgba[3] <= 0:
        return None
    rgb = rgba[3] * rgba[:3] + (1 - rgba[3]) * SEEN_THROUGH
    texture = assets.textures.get(material.get("texture", ""))
    if texture is not None:
        repeat = _floats(material.get("texrepeat"), (1, 1))
        return box_projected(triangles, load_image(texture), repeat, rgb)
    faces = np.arange(3 * len(triangles)).reshape(-1, 3)
    return ColourSource(faces, factor=rgb)


def assemble(xml: Path, assets: Assets, body: str = "") -> list[Part]:
    """Visible geoms of ``body`` (default: the file's first body) and its descendants."""
    root = ET.parse(xml).getroot()
    local = read_assets([xml], [xml.parent])  # full <mujoco> files declare their own assets
    merged = Assets(
        {**assets.meshes, **local.meshes},
        {**assets.textures, **local.textures},
        {**assets.materials, **local.materials},
        {**assets.defaults, **local.defaults},
        assets.degrees or local.degrees,
    )
    bodies = [b for b in root.iter("body") if not body or b.get("name") == body]
    if not bodies:
        raise ValueError(f"{xml} has no body named {body!r}")
    parents = {child: node for node in root.iter() for child in node}
    node, cls = bodies[0], "main"
    while node is not None:  # the innermost childclass among the body and its ancestors applies
        if node.get("childclass"):
            cls = node.get("childclass")
            break
        node = parents.get(node)
    parts: list[Part] = []
    _walk(bodies[0], np.eye(4), cls, merged, parts, set())
    if not parts:
        raise ValueError(f"{xml}: body {body or bodies[0].get('name')!r} has no visible geom")
    return parts


def _walk(node: ET.Element, T: np.ndarray, cls: str, assets: Assets, parts: list[Part], seen: set) -> None:
    for geom in node.findall("geom"):
        attrs = {**assets.defaults.get(geom.get("class", cls), {}), **geom.attrib}
        if int(attrs.get("group", 0)) in HIDDEN_GROUPS:
            continue
        G = T @ frame(attrs, assets.degrees)
        kind = attrs.get("type", "sphere")
        if kind == "mesh":
            file, scale = assets.meshes[attrs["mesh"]]
            mesh = trimesh.load(str(file), force="mesh")
            tri, name = np.asarray(mesh.vertices)[mesh.faces] * scale, attrs["mesh"]
        else:
            fromto = _floats(attrs["fromto"]) if "fromto" in attrs else None
            mesh, extra = _primitive(kind, _floats(attrs.get("size")), fromto)
            G = (T @ extra) if fromto is not None else G
            tri, name = np.asarray(mesh.vertices)[mesh.faces], kind
        tri = tri @ G[:3, :3].T + G[:3, 3]
        key = np.round(tri, 9).tobytes()  # the same geom twice (a visual and a collision copy)
        colour = _colour(attrs, assets, tri)
        if colour is None or key in seen:
            continue
        seen.add(key)
        parts.append(Part(tri, colour, name))
    for child in node.findall("body"):
        _walk(
            child, T @ frame(child.attrib, assets.degrees), child.get("childclass", cls), assets, parts, seen
        )
