"""Import textured meshes as PhysAssets: ``python -m physgm.data.from_meshes``.

    python -m physgm.data.from_meshes --meshes DIR_OR_FILES... --material NAME --out DIR
        [--E PA --nu NU --density KG_M3] [--resolution 128] [--up auto|y|z] [--split train]

Each mesh (OBJ, GLB/GLTF, PLY, STL, OFF, anything trimesh loads) is normalised to the asset
frame (bounding-box centre at the origin, farthest vertex at radius 0.5, +z up; GLB/GLTF are
+y up by specification, so ``--up auto`` rotates those) and rendered offline on the CPU by ray
casting (raycast.py) from the same 32 views as the synthetic assets: colour from the texture,
vertex or face colours at the hit, Lambertian + ambient shading under the same light as the
synthetic assets, supersampled for anti-aliased edges. Without --E/--nu/--density the material table's
typical values are written and marked as such.

Asset ids are the mesh's path relative to the folder it was found in, without the suffix
(``chair/model.obj`` -> ``chair__model``; a file given directly -> its stem), so they are stable
across runs. Files whose ids would coincide (``a/model.obj`` and ``a/model.glb``, the same
relative path under two folders) get a hash suffix instead, and an id already on disk from a
different mesh file stops the import: two objects never become one asset (mesh_ids.py).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from physgm.data.appearance import AMBIENT, LIGHT_DIR
from physgm.data.format import SPLITS
from physgm.data.mesh_ids import (
    add_to_split,
    asset_id_for,
    assign_ids,
    count_assets,
    existing_import,
    file_sha1,
    find_meshes,
)
from physgm.data.priors import constitutive_model, material_names
from physgm.data.raycast import cast_rays
from physgm.data.synth import view_cameras
from physgm.data.writer import atomic_asset_dir, write_views_cameras_physics
from physgm.physics.materials import get_material

DEFAULT_GREY = 0.7  # albedo of meshes without colours


@dataclass
class ColourSource:
    """How to colour hits on one mesh."""

    faces: np.ndarray  # [F, 3] vertex indices
    uv: np.ndarray | None = None  # [V, 2]
    image: np.ndarray | None = None  # [H, W, 3] float in [0, 1]
    vertex_colors: np.ndarray | None = None  # [V, 3]
    face_colors: np.ndarray | None = None  # [F, 3]
    factor: np.ndarray | None = None  # [3] constant colour / multiplier

    def sample(self, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Albedo [K, 3] at hits on local faces [K] with barycentrics [K, 3]."""
        factor = np.ones(3) if self.factor is None else self.factor
        if self.image is not None and self.uv is not None:
            uv = np.einsum("kj,kjd->kd", bary, self.uv[self.faces[face]]) % 1.0
            return _bilinear(self.image, uv) * factor
        if self.vertex_colors is not None:
            return np.einsum("kj,kjd->kd", bary, self.vertex_colors[self.faces[face]])
        if self.face_colors is not None:
            return self.face_colors[face]
        return np.tile(factor if self.factor is not None else np.full(3, DEFAULT_GREY), (len(face), 1))


def _bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    x, y = uv[:, 0] * (w - 1), (1.0 - uv[:, 1]) * (h - 1)  # texture v points up, image rows down
    x0, y0 = np.clip(np.floor(x).astype(int), 0, w - 1), np.clip(np.floor(y).astype(int), 0, h - 1)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def colour_source(mesh: trimesh.Trimesh) -> ColourSource:
    """Read the colour information trimesh found for a mesh."""
    vis = mesh.visual
    src = ColourSource(np.asarray(mesh.faces))
    if getattr(vis, "kind", None) == "texture":
        mat = vis.material
        image = getattr(mat, "baseColorTexture", None) or getattr(mat, "image", None)
        factor = getattr(mat, "baseColorFactor", None)
        if factor is None:
            factor = getattr(mat, "main_color", None) if image is None else None
        if factor is not None:
            src.factor = np.asarray(factor, dtype=np.float64)[:3] / 255.0
        if image is not None and vis.uv is not None:
            src.image = np.asarray(image.convert("RGB"), dtype=np.float64) / 255.0
            src.uv = np.asarray(vis.uv, dtype=np.float64)
    elif getattr(vis, "kind", None) == "vertex":
        src.vertex_colors = np.asarray(vis.vertex_colors, dtype=np.float64)[:, :3] / 255.0
    elif getattr(vis, "kind", None) == "face":
        src.face_colors = np.asarray(vis.face_colors, dtype=np.float64)[:, :3] / 255.0
    return src


@dataclass
class MeshObject:
    """All triangles of a mesh file in the asset frame, with colour sources per part."""

    triangles: np.ndarray  # [M, 3, 3]
    part: np.ndarray  # [M] index into sources
    local_face: np.ndarray  # [M] face index within its part
    sources: list[ColourSource]


def up_rotation(path: Path, up: str) -> np.ndarray:  # [3, 3]
    """The rotation that brings a mesh file's up axis to +z. ``up``: "y", "z", or "auto" (+y for
    glTF, as its specification says, +z for the other formats)."""
    y_up = up == "y" or (up == "auto" and path.suffix.lower() in (".glb", ".gltf"))
    return np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]) if y_up else np.eye(3)  # +y -> +z


def load_mesh(path: Path, up: str = "auto") -> MeshObject:
    """Load every triangle mesh in a file, z-up, centred, farthest vertex at radius 0.5."""
    try:
        scene = trimesh.load(str(path), force="scene")
    except Exception as err:
        raise ValueError(f"trimesh could not read {path} ({err}); convert it to OBJ, GLB or PLY") from err
    meshes = [g for g in scene.dump(concatenate=False) if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    if not meshes:
        raise ValueError(f"{path} holds no triangle mesh")
    rot = up_rotation(path, up)
    tris = [np.asarray(m.vertices, dtype=np.float64)[m.faces] @ rot.T for m in meshes]
    verts = np.concatenate([t.reshape(-1, 3) for t in tris])
    centre = (verts.min(0) + verts.max(0)) / 2
    radius = float(np.linalg.norm(verts - centre, axis=1).max())
    if not radius > 0:
        raise ValueError(f"{path}: the mesh is degenerate (all vertices at one point)")
    tri = (np.concatenate(tris) - centre) * (0.5 / radius)
    part = np.concatenate([np.full(len(m.faces), i) for i, m in enumerate(meshes)])
    local = np.concatenate([np.arange(len(m.faces)) for m in meshes])
    return MeshObject(tri, part, local, [colour_source(m) for m in meshes])


def render_mesh(obj: MeshObject, resolution: int, supersample: int = 2) -> np.ndarray:
    """Straight-alpha uint8 RGBA [32, H, W, 4] of the 32 synthetic views."""
    cams, _, _ = view_cameras(resolution * supersample)
    e1, e2 = obj.triangles[:, 1] - obj.triangles[:, 0], obj.triangles[:, 2] - obj.triangles[:, 0]
    normals = np.cross(e1, e2)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
    out = []
    for c in range(len(cams)):
        c2w, K = cams.c2w[c].double().numpy(), cams.Ks[c].double().numpy()
        size = resolution * supersample
        hits = cast_rays(obj.triangles, c2w, K, size, size)
        mask = hits.face >= 0
        rgb = np.ones((size, size, 3))
        f = hits.face[mask]
        albedo = np.zeros((len(f), 3))
        for i, src in enumerate(obj.sources):
            sel = obj.part[f] == i
            albedo[sel] = src.sample(obj.local_face[f[sel]], hits.bary[mask][sel])
        n = normals[f]
        view = obj.triangles[f, 0] - c2w[:3, 3]
        n = np.where((np.einsum("kd,kd->k", n, view) > 0)[:, None], -n, n)  # two-sided: face the camera
        shade = AMBIENT + (1 - AMBIENT) * np.clip(n @ LIGHT_DIR, 0, 1)
        rgb[mask] = np.clip(albedo * shade[:, None], 0, 1)
        a = mask.astype(np.float64)
        # Box-filter the supersamples: premultiplied colour and coverage average exactly.
        blk = lambda x: x.reshape(resolution, supersample, resolution, supersample, -1).mean((1, 3))  # noqa: E731
        alpha = blk(a[..., None])
        straight = np.where(alpha > 0, blk(rgb * a[..., None]) / np.maximum(alpha, 1e-12), 1.0)
        out.append(np.concatenate([np.round(straight * 255), np.round(alpha * 255)], -1).astype(np.uint8))
    return np.stack(out)


def default_physics(material: str) -> dict:
    """Typical values of a material from the material table."""
    m = get_material(material)
    return {"E": m.E, "nu": m.nu, "density": m.density}


def import_mesh(
    path: Path,
    out: Path,
    material: str,
    resolution: int = 128,
    supersample: int = 2,
    up: str = "auto",
    physics: dict | None = None,
    asset_id: str | None = None,
    mesh_name: str | None = None,
) -> str:
    """Render one mesh file into ``out/<asset_id>``; returns the id ("" if this mesh is already there).

    ``asset_id`` defaults to the file's stem and ``mesh_name`` (recorded as ``mesh_file``) to its
    name; an existing folder of that id made from another mesh raises ValueError.
    """
    if material not in material_names():
        raise ValueError(f"unknown material {material!r}; choose one of {', '.join(material_names())}")
    aid = asset_id or asset_id_for(path)
    digest = file_sha1(path)
    if existing_import(out, aid, path, digest):
        return ""
    given = {k: v for k, v in (physics or {}).items() if v is not None}
    values = {**default_physics(material), **given}
    if not (values["E"] > 0 and -1 < values["nu"] < 0.5 and values["density"] > 0):
        raise ValueError(f"impossible physics {values}: need E > 0 Pa, -1 < nu < 0.5, density > 0")
    rgba = render_mesh(load_mesh(path, up), resolution, supersample)
    cams, az, el = view_cameras(resolution)
    physical = {
        "material": material,
        **{k: float(v) for k, v in values.items()},
        "constitutive_model": constitutive_model(material),
        "source": "mesh",
        "mesh_file": mesh_name or path.name,
        "mesh_sha1": digest,  # tells a re-import of this mesh from a different mesh with the same id
        "physics_source": "user" if {"E", "nu"} <= set(given) else "material default",
    }
    with atomic_asset_dir(out, aid) as tmp:
        write_views_cameras_physics(tmp, rgba, cams, az, el, physical)
    return aid


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m physgm.data.from_meshes", description="Import meshes as PhysAssets."
    )
    p.add_argument(
        "--meshes", nargs="+", required=True, help="mesh files and/or folders (searched recursively)"
    )
    p.add_argument("--material", required=True, choices=list(material_names()))
    p.add_argument("--out", type=Path, required=True)
    p.add_argument(
        "--E", type=float, default=None, help="Young's modulus, Pa (default: typical for the material)"
    )
    p.add_argument("--nu", type=float, default=None, help="Poisson's ratio (default: typical)")
    p.add_argument("--density", type=float, default=None, help="kg/m^3 (default: typical)")
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--supersample", type=int, default=2, help="rays per pixel side, for anti-aliased edges")
    p.add_argument(
        "--up",
        choices=["auto", "y", "z"],
        default="auto",
        help="up axis of the files (auto: y for GLB/GLTF, else z)",
    )
    p.add_argument(
        "--split", choices=list(SPLITS), default="train", help="split list the imported assets join"
    )
    a = p.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    meshes = find_meshes(a.meshes)
    try:
        ids = assign_ids(meshes)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    imported, present, failed = [], [], {}
    for m in meshes:
        aid = ids[m.path]
        try:
            new = import_mesh(
                m.path,
                a.out,
                a.material,
                a.resolution,
                a.supersample,
                a.up,
                {"E": a.E, "nu": a.nu, "density": a.density},
                asset_id=aid,
                mesh_name=m.relative,
            )
            (imported if new else present).append(aid)
        except (ValueError, OSError) as err:
            failed[str(m.path)] = str(err)
            print(f"could not import {m.path}: {err}", file=sys.stderr)
    try:
        add_to_split(a.out, a.split, imported + present)
    except ValueError as err:
        failed["splits"] = str(err)
        print(f"split list {a.split}: {err}", file=sys.stderr)
    renamed = {str(m.path): ids[m.path] for m in meshes if ids[m.path] != asset_id_for(m.path, m.root)}
    report = {
        "imported": len(imported),  # new asset folders written by this run
        "already_present": len(present),  # this run's meshes found imported before
        "assets_on_disk": count_assets(a.out),
        "renamed": renamed,  # mesh file -> id with a hash suffix (names that would collide)
        "failed": failed,
        "out": str(a.out),
    }
    print(json.dumps(report))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
