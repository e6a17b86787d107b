"""physgm's own real-object sets: ``python -m physgm.data.real_objects``.

    python -m physgm.data.real_objects --out data/real_objects [--resolution 256] [--only ID,ID]
    python -m physgm.data.real_objects --set gate --out data/real_gate

Builds PhysAssets from artist-made, textured objects that three pip packages ship (robosuite
1.5.2, genesis-world 1.4.5 and metaworld 3.1.1, installed ``--no-deps`` by scripts/setup.sh;
only their asset files are read, no package is imported). Each object is a row of a table
(``physgm.data.real_object_tables``): its mesh file, or its MJCF body assembled from parts
(mjcf.py), a hand label (one of the 15 materials of the material table) and why. Rendering is
the mesh importer's (from_meshes.render_mesh: same 32 views, light and normalisation as the
synthetic assets).

Two sets, each built into its own root (``SETS``):

* ``eval`` (``OBJECTS``, the default): the evaluation set. robosuite's and genesis-world's
  objects go to ``val`` (used only to choose hyper-parameters such as a fusion weight),
  metaworld's to ``test``; ``train`` and ``dpo`` stay empty, so the set is never trained on.
* ``gate`` (``GATE_OBJECTS``): other objects of the same packages, none of them an evaluation
  object or a near-copy of one, all in ``train``. They train only the domain gate (a classifier
  telling procedural synthetic renders from real objects), which reads the images, not the
  labels; their labels are best effort, because the asset format needs one.

physical.json holds the hand label with the material table's typical E, nu and density
(``physics_source: "material default"``), ``label_source: "hand"`` and the reason.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from dataclasses import asdict
from pathlib import Path

import numpy as np
import trimesh

from physgm.data import mjcf
from physgm.data.asset_packages import distribution, package_root, package_version, requirement
from physgm.data.format import SPLITS, SPLITS_DIR
from physgm.data.from_meshes import (
    ColourSource,
    MeshObject,
    colour_source,
    default_physics,
    render_mesh,
    up_rotation,
)
from physgm.data.priors import constitutive_model, material_names
from physgm.data.real_object_tables import SEARCH_DIRS, SETS, RealObject
from physgm.data.synth import view_cameras
from physgm.data.writer import atomic_asset_dir, write_json, write_views_cameras_physics


def _files(obj: RealObject, root: Path) -> list[Path]:
    return [root / f for f in (obj.mesh, obj.xml, *obj.deps, obj.texture) if f]


def _mesh_parts(obj: RealObject, root: Path) -> list[mjcf.Part]:
    rot = up_rotation(root / obj.mesh, obj.up)
    parts = []
    for path in (root / f for f in (obj.mesh, *obj.deps)):
        parts += _file_parts(obj, root, path, rot)
    return parts


def _file_parts(obj: RealObject, root: Path, path: Path, rot: np.ndarray) -> list[mjcf.Part]:
    # robosuite's MTL files name their textures as ../../textures/x.png, outside the mesh folder,
    # which trimesh >= 5 refuses unless asked (the file is inside the installed package).
    resolver = trimesh.resolvers.FilePathResolver(str(path), allow_anywhere=True)
    scene = trimesh.load(str(path), force="scene", resolver=resolver)
    parts = []
    for mesh in scene.dump(concatenate=False):
        tri = np.asarray(mesh.vertices, dtype=np.float64)[mesh.faces] @ rot.T
        if obj.texture:
            image = mjcf.load_image(root / obj.texture)
            colour = mjcf.box_projected(tri, image, np.ones(2), np.ones(3))
        elif obj.rgba is not None:
            colour = ColourSource(np.arange(3 * len(tri)).reshape(-1, 3), factor=np.asarray(obj.rgba))
        else:
            colour = colour_source(mesh)
        parts.append(mjcf.Part(tri, colour, path.name))
    return parts


def load_object(obj: RealObject) -> MeshObject:
    """The object's triangles in the asset frame (+z up, bounding-box centre at 0, radius 0.5)."""
    root = package_root(obj.source)
    missing = [str(f) for f in _files(obj, root) if not f.is_file()]
    if missing:
        raise FileNotFoundError(
            f"{obj.id}: {missing} not in the installed {obj.source} {package_version(obj.source)}; "
            f"the table is for {requirement(obj.source)} (pip install --no-deps {requirement(obj.source)})"
        )
    if obj.mesh:
        parts = _mesh_parts(obj, root)
    else:
        search = [root / d for d in SEARCH_DIRS[obj.source]]
        assets = mjcf.read_assets([root / d for d in obj.deps], search)
        parts = mjcf.assemble(root / obj.xml, assets, obj.body)
    yaw = np.deg2rad(obj.yaw_deg)
    rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    tri = np.concatenate([p.triangles for p in parts]) @ rot.T
    verts = tri.reshape(-1, 3)
    centre = (verts.min(0) + verts.max(0)) / 2
    radius = float(np.linalg.norm(verts - centre, axis=1).max())
    return MeshObject(
        (tri - centre) * (0.5 / radius),
        np.concatenate([np.full(len(p.triangles), i) for i, p in enumerate(parts)]),
        np.concatenate([np.arange(len(p.triangles)) for p in parts]),
        [p.colour for p in parts],
    )


def build_object(obj: RealObject, out: Path, resolution: int, supersample: int) -> None:
    """Render one object into ``out/<id>`` (atomically)."""
    rgba = render_mesh(load_object(obj), resolution, supersample)
    cams, az, el = view_cameras(resolution)
    root = package_root(obj.source)
    physical = {
        "material": obj.material,
        **{k: float(v) for k, v in default_physics(obj.material).items()},
        "constitutive_model": constitutive_model(obj.material),
        "physics_source": "material default",
        "source": "real object, hand-labelled",
        "label_source": "hand",
        "label_reason": obj.reason,
        "package": f"{distribution(obj.source)}=={package_version(obj.source)}",
        "files": [str(f.relative_to(root)) for f in _files(obj, root)],
    }
    with atomic_asset_dir(out, obj.id) as tmp:
        write_views_cameras_physics(tmp, rgba, cams, az, el, physical)


def select(only: list[str] | None, set_name: str = "eval") -> list[RealObject]:
    """The set's objects, or the ``only`` ones; a label outside the material table stops here."""
    table = SETS[set_name].objects
    bad = {o.id: o.material for o in table if o.material not in material_names()}
    if bad:
        raise ValueError(
            f"{set_name} set labels {bad} are not materials of the table ({', '.join(material_names())})"
        )
    if not only:
        return list(table)
    known = {o.id: o for o in table}
    unknown = [i for i in only if i not in known]
    if unknown:
        elsewhere = {n for n, other in SETS.items() for o in other.objects if o.id in unknown} - {set_name}
        hint = f" (they are in the {', '.join(sorted(elsewhere))} set: add --set)" if elsewhere else ""
        raise ValueError(
            f"unknown object ids {unknown} in the {set_name} set{hint}; known: {', '.join(known)}"
        )
    return [known[i] for i in only]


def build(
    out: Path,
    resolution: int = 256,
    supersample: int = 2,
    only: list[str] | None = None,
    set_name: str = "eval",
) -> dict:
    """Build set ``set_name`` (or its ``only`` objects) into ``out``; finished objects are kept.

    Returns a summary: objects built and skipped, seconds, and the count per split and material.

    Raises:
        ValueError: ``out`` holds the other set, or was built with other settings.
    """
    real_set = SETS[set_name]
    objects = select(only, set_name)
    settings = {"resolution": resolution, "supersample": supersample}
    manifest = out / "real_objects.json"
    if manifest.is_file():
        have = json.loads(manifest.read_text())
        held = have.get("set", "eval")  # manifests written before the gate set hold the eval set
        if held != set_name:
            raise ValueError(
                f"{out} holds the {held} set; the {set_name} set goes into its own root: use another --out"
            )
        if have["settings"] != settings:
            raise ValueError(
                f"{out} was built with {have['settings']}, not {settings}; use another --out or delete it"
            )
    out.mkdir(parents=True, exist_ok=True)
    t0, built, kept = time.perf_counter(), [], []
    for obj in objects:
        if (out / obj.id).is_dir():
            kept.append(obj.id)
            continue
        build_object(obj, out, resolution, supersample)
        built.append(obj.id)
    present = [o for o in real_set.objects if (out / o.id).is_dir()]
    (out / SPLITS_DIR).mkdir(exist_ok=True)
    for split in SPLITS:
        ids = [o.id for o in present if real_set.split_of(o) == split]
        (out / SPLITS_DIR / f"{split}.txt").write_text("".join(f"{i}\n" for i in ids))
    table = [{**asdict(o), "split": real_set.split_of(o)} for o in present]
    write_json(manifest, {"set": set_name, "settings": settings, "objects": table})
    return {
        "set": set_name,
        "built": built,
        "kept": kept,
        "seconds": round(time.perf_counter() - t0, 1),
        "splits": {s: sum(real_set.split_of(o) == s for o in present) for s in SPLITS},
        "materials": dict(Counter(o.material for o in present)),
        "out": str(out),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m physgm.data.real_objects", description=__doc__.splitlines()[0]
    )
    p.add_argument("--out", type=Path, required=True)
    p.add_argument(
        "--set",
        dest="set_name",
        choices=list(SETS),
        default="eval",
        help="eval: the evaluation set (val/test); gate: the domain gate's training set (all train)",
    )
    p.add_argument("--resolution", type=int, default=256, help="px; the ImageNet classifier reads it all")
    p.add_argument("--supersample", type=int, default=2, help="rays per pixel side, for anti-aliased edges")
    p.add_argument("--only", default="", help="comma-separated object ids of the set (default: all)")
    a = p.parse_args(argv)
    only = [s for s in a.only.split(",") if s] or None
    print(json.dumps(build(a.out, a.resolution, a.supersample, only, a.set_name)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
