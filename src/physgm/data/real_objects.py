"""physgm's own real-object evaluation set: ``python -m physgm.data.real_objects``.

    python -m physgm.data.real_objects --out data/real_objects [--resolution 256] [--only ID,ID]

Builds PhysAssets from artist-made, textured objects that three pip packages ship (robosuite
1.5.2, genesis-world 1.4.5 and metaworld 3.1.1, installed ``--no-deps`` by scripts/setup.sh;
only their asset files are read, no package is imported). Each object is a row of ``OBJECTS``:
its mesh file, or its MJCF body assembled from parts (mjcf.py), a hand label (one of the 15
materials of the material table) and why. Rendering is the mesh importer's
(from_meshes.render_mesh: same 32 views, light and normalisation as the synthetic assets).

Splits: robosuite's and genesis-world's objects go to ``val`` (used only to choose
hyper-parameters such as a fusion weight), metaworld's to ``test``; ``train`` and ``dpo`` stay
empty, so the set is never trained on. physical.json holds the hand label with the material
table's typical E, nu and density (``physics_source: "material default"``),
``label_source: "hand"`` and the reason.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from dataclasses import asdict, dataclass
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
from physgm.data.synth import view_cameras
from physgm.data.writer import atomic_asset_dir, write_json, write_views_cameras_physics

SPLIT_OF_SOURCE = {"robosuite": "val", "genesis": "val", "metaworld": "test"}
# MJCF files name meshes and textures relative to the top-level model's folder.
SEARCH_DIRS = {"robosuite": ("models/assets/objects",), "metaworld": ("assets/sawyer_xyz",)}
MW = "assets/objects/assets/"  # metaworld's object MJCF folder
RS = "models/assets/objects/"  # robosuite's
GN = "assets/meshes/"  # genesis-world's


@dataclass(frozen=True)
class RealObject:
    """One object of the set: where its geometry and colours are, and its hand label."""

    id: str
    source: str  # module of the pip package holding the files: "robosuite", "genesis" or "metaworld"
    material: str  # hand label, one of MATERIAL_NAMES
    reason: str  # why that material
    mesh: str = ""  # a mesh file in the package (OBJ with its MTL texture, GLB, or STL) ...
    xml: str = ""  # ... or an MJCF file whose body is assembled from its geoms
    deps: tuple[str, ...] = ()  # MJCF files declaring its meshes, materials and default classes
    body: str = ""  # MJCF body to start from (default: the file's first)
    rgba: tuple[float, float, float] | None = None  # colour of a `mesh` that has none of its own
    texture: str = ""  # box-projected texture for a `mesh` without texture coordinates
    yaw_deg: float = 0.0  # turn about +z so the object's front faces +x (view 000)
    up: str = "auto"  # the mesh file's up axis (from_meshes.up_rotation): "y", "z" or "auto"

    @property
    def split(self) -> str:
        return SPLIT_OF_SOURCE[self.source]


def _mw(id, material, reason, xml, deps="", **kw) -> RealObject:
    """A metaworld MJCF object; its dependencies file is ``<xml stem>_dependencies.xml`` unless named."""
    deps = deps or xml.removesuffix(".xml") + "_dependencies.xml"
    return RealObject(id, "metaworld", material, reason, xml=MW + xml, deps=(MW + deps,), **kw)


OBJECTS: tuple[RealObject, ...] = (
    # robosuite -> val
    RealObject(
        "rs_bottle",
        "robosuite",
        "glass",
        "a green glass bottle (robosuite draws it with its glass texture)",
        mesh=RS + "meshes/bottle.obj",
        texture="models/assets/textures/glass.png",
    ),
    RealObject(
        "rs_can",
        "robosuite",
        "metal",
        "an aluminium soda can with a printed label",
        mesh=RS + "meshes/can.obj",
    ),
    RealObject(
        "rs_cereal",
        "robosuite",
        "paper",
        "a printed cardboard cereal box",
        mesh=RS + "meshes/cereal.obj",
        yaw_deg=-90,
    ),
    RealObject(
        "rs_milk", "robosuite", "paper", "a milk carton: coated paperboard", mesh=RS + "meshes/milk.obj"
    ),
    RealObject(
        "rs_bread",
        "robosuite",
        "foam",
        "a bread roll: a porous solid foam that squashes and springs back, "
        "the closest of the 15 in behaviour",
        mesh=RS + "meshes/bread.obj",
    ),
    RealObject(
        "rs_round_nut",
        "robosuite",
        "metal",
        "a large steel nut (scratched-steel texture)",
        xml=RS + "round-nut.xml",
    ),
    RealObject(
        "rs_square_nut",
        "robosuite",
        "metal",
        "a large steel nut (scratched-steel texture)",
        xml=RS + "square-nut.xml",
    ),
    RealObject(
        "rs_plate_with_hole",
        "robosuite",
        "wood",
        "a flat board with a square hole, red-wood texture",
        xml=RS + "plate-with-hole.xml",
    ),
    RealObject(
        "rs_door",
        "robosuite",
        "wood",
        "a dark-wood door panel (most of the object) with a brass handle in a white frame",
        xml=RS + "door.xml",
    ),
    # genesis-world -> val: the meshes its examples drop, cut and pour
    RealObject(
        "gn_duck", "genesis", "rubber", "a yellow rubber bath duck", mesh=GN + "duck/duck.obj", up="y"
    ),
    RealObject(
        "gn_ball",
        "genesis",
        "rubber",
        "a plain black toy ball, as bouncy balls are",
        mesh="assets/tower/ball.glb",
    ),
    RealObject(
        "gn_wooden_sphere",
        "genesis",
        "wood",
        "a turned wooden sphere with visible grain",
        mesh=GN + "wooden_sphere_OBJ/wooden_sphere.obj",
    ),
    RealObject(
        "gn_chopping_board",
        "genesis",
        "wood",
        "a pale wooden chopping board with a handle slot",
        mesh=GN + "chopping-board/source/chopping_board.glb",
    ),
    RealObject(
        "gn_boat", "genesis", "wood", "a planked, red-painted rowing boat", mesh=GN + "boat/boat.obj", up="y"
    ),
    RealObject(
        "gn_water_wheel",
        "genesis",
        "wood",
        "a water wheel: wooden rim, spokes and paddles",
        mesh="assets/urdf/wheel/fancy_wheel.obj",
    ),
    RealObject(
        "gn_bathtub",
        "genesis",
        "ceramic",
        "a bathtub: glazed enamel or ceramic",
        mesh=GN + "bathtub/bathtub.obj",
        up="y",
    ),
    RealObject(
        "gn_bunny",
        "genesis",
        "ceramic",
        "the Stanford bunny, scanned from a terracotta figurine; drawn plain grey",
        mesh=GN + "bunny.obj",
    ),
    RealObject(
        "gn_dragon",
        "genesis",
        "stone",
        "a green dragon figurine, like carved jade",
        mesh=GN + "dragon/dragon.obj",
        up="y",
    ),
    RealObject(
        "gn_airplane",
        "genesis",
        "metal",
        "a light aircraft: aluminium skin",
        mesh=GN + "Airplane/airplane.obj",
        up="y",
    ),
    RealObject(
        "gn_dispenser",
        "genesis",
        "metal",
        "an ice-cream dispenser: a stainless-steel machine (untextured)",
        mesh=GN + "icecream_dispenser.obj",
        up="y",
    ),
    RealObject("gn_stirrer", "genesis", "metal", "a thin steel stirring rod", mesh=GN + "stirrer.obj"),
    # metaworld -> test
    _mw(
        "mw_mug",
        "ceramic",
        "a white coffee mug with a handle",
        "mug.xml",
        "coffeemachine_dependencies.xml",
        yaw_deg=90,
    ),
    RealObject(
        "mw_cup",
        "metaworld",
        "ceramic",
        "the coffee machine's espresso cup (a mesh no geom uses), coloured like the mug",
        mesh="assets/objects/meshes/coffeemachine/cup.stl",
        rgba=(0.85, 0.85, 0.85),
    ),
    _mw("mw_basketball", "rubber", "a basketball: orange rubber with black seams", "basketball.xml"),
    _mw(
        "mw_soccer_ball",
        "leather",
        "a black-and-white panelled football; panels are (synthetic) leather",
        "soccer_ball.xml",
        "soccer_dependencies.xml",
    ),
    _mw(
        "mw_puck",
        "rubber",
        "a black ice-hockey puck: vulcanised rubber",
        "puck.xml",
        "puck_goal_dependencies.xml",
    ),
    _mw("mw_nail", "metal", "a steel nail", "hammerblock.xml", "hammer_dependencies.xml", body="nail_link"),
    _mw(
        "mw_hammer_block",
        "wood",
        "a wooden block with a nail in it; the block is nearly all of it",
        "hammerblock.xml",
        "hammer_dependencies.xml",
        yaw_deg=90,
    ),
    _mw(
        "mw_safe",
        "metal",
        "a steel safe with a handle and a lock",
        "doorlockA.xml",
        "doorlock_dependencies.xml",
        yaw_deg=90,
    ),
    _mw(
        "mw_laptop",
        "plastic",
        "an open laptop, grey plastic shell and black screen",
        "laptop.xml",
        yaw_deg=90,
    ),
    _mw(
        "mw_shelf", "wood", "a wooden shelf unit (wood texture) with white supports", "shelf.xml", yaw_deg=90
    ),
    _mw(
        "mw_bin", "plastic", "a glossy red storage tray: moulded plastic", "binA.xml", "bin_dependencies.xml"
    ),
    _mw("mw_box", "wood", "an open box with a wood texture", "box.xml"),
    _mw("mw_faucet", "metal", "a tap: metal body and spout with a red lever", "faucet.xml"),
    _mw("mw_thermos", "metal", "a steel thermos flask with a handle", "thermos.xml", yaw_deg=90),
    _mw(
        "mw_button_box",
        "plastic",
        "a yellow-and-black stop-button box with a red push button",
        "buttonbox.xml",
        yaw_deg=90,
    ),
    _mw("mw_block", "wood", "a wooden toy cube (wood texture)", "block.xml"),
    _mw("mw_peg_block", "wood", "a wooden block with a red-lined peg hole", "peg_block.xml", yaw_deg=90),
    _mw("mw_table", "wood", "a wooden table", "table.xml"),
    _mw(
        "mw_coffee_machine",
        "plastic",
        "a coffee machine with a moulded dark-red and black plastic body",
        "coffeemachine.xml",
        yaw_deg=90,
    ),
    _mw("mw_lever", "metal", "a metal lever arm on a metal base with a blue knob", "lever.xml", yaw_deg=90),
    _mw(
        "mw_wall",
        "stone",
        "a brick wall section: fired-clay masonry, rigid, matte and rough like stone",
        "wall.xml",
        yaw_deg=90,
    ),
    _mw(
        "mw_window",
        "glass",
        "a sash window: two large panes of glass in a thin frame",
        "window.xml",
        yaw_deg=90,
    ),
)
# Left out on purpose: robosuite's lemon (no material of the 15 behaves like fruit flesh); metaworld's
# dial (its dark metal texture renders as black plastic without MuJoCo's reflections), hammer and
# golf club (half wood or plastic, half metal), drawer and stick (painted, material unreadable), the
# goals and hoop (nets and frames), and the robot itself; genesis-world's worm (soft tissue), tank (a
# plain container of unreadable material), camera (a flat dark silhouette), the cloth, terrain,
# environment sphere and the robots.


def _files(obj: RealObject, root: Path) -> list[Path]:
    return [root / f for f in (obj.mesh, obj.xml, *obj.deps, obj.texture) if f]


def _mesh_parts(obj: RealObject, root: Path) -> list[mjcf.Part]:
    path = root / obj.mesh
    # robosuite's MTL files name their textures as ../../textures/x.png, outside the mesh folder,
    # which trimesh >= 5 refuses unless asked (the file is inside the installed package).
    resolver = trimesh.resolvers.FilePathResolver(str(path), allow_anywhere=True)
    scene = trimesh.load(str(path), force="scene", resolver=resolver)
    rot = up_rotation(path, obj.up)
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
        parts.append(mjcf.Part(tri, colour, Path(obj.mesh).name))
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


def select(only: list[str] | None) -> list[RealObject]:
    """The table's objects, or the ``only`` ones; a label outside the material table stops here."""
    bad = {o.id: o.material for o in OBJECTS if o.material not in material_names()}
    if bad:
        raise ValueError(
            f"OBJECTS labels {bad} are not materials of the table ({', '.join(material_names())})"
        )
    if not only:
        return list(OBJECTS)
    known = {o.id: o for o in OBJECTS}
    unknown = [i for i in only if i not in known]
    if unknown:
        raise ValueError(f"unknown object ids {unknown}; known: {', '.join(known)}")
    return [known[i] for i in only]


def build(out: Path, resolution: int = 256, supersample: int = 2, only: list[str] | None = None) -> dict:
    """Build the set (or the ``only`` objects) into ``out``; finished objects are kept.

    Returns a summary: objects built and skipped, seconds, and the count per split and material.
    """
    objects = select(only)
    settings = {"resolution": resolution, "supersample": supersample}
    manifest = out / "real_objects.json"
    if manifest.is_file():
        have = json.loads(manifest.read_text())["settings"]
        if have != settings:
            raise ValueError(f"{out} was built with {have}, not {settings}; use another --out or delete it")
    out.mkdir(parents=True, exist_ok=True)
    t0, built, kept = time.perf_counter(), [], []
    for obj in objects:
        if (out / obj.id).is_dir():
            kept.append(obj.id)
            continue
        build_object(obj, out, resolution, supersample)
        built.append(obj.id)
    listed = {o.id for o in OBJECTS if (out / o.id).is_dir()}
    (out / SPLITS_DIR).mkdir(exist_ok=True)
    for split in SPLITS:
        ids = [o.id for o in OBJECTS if o.split == split and o.id in listed]
        (out / SPLITS_DIR / f"{split}.txt").write_text("".join(f"{i}\n" for i in ids))
    table = [{**asdict(o), "split": o.split} for o in OBJECTS if o.id in listed]
    write_json(manifest, {"settings": settings, "objects": table})
    present = [o for o in OBJECTS if o.id in listed]
    return {
        "built": built,
        "kept": kept,
        "seconds": round(time.perf_counter() - t0, 1),
        "splits": {s: sum(o.split == s for o in present) for s in SPLITS},
        "materials": dict(Counter(o.material for o in present)),
        "out": str(out),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m physgm.data.real_objects", description=__doc__.splitlines()[0]
    )
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--resolution", type=int, default=256, help="px; the ImageNet classifier reads it all")
    p.add_argument("--supersample", type=int, default=2, help="rays per pixel side, for anti-aliased edges")
    p.add_argument("--only", default="", help="comma-separated object ids (default: all)")
    a = p.parse_args(argv)
    summary = build(a.out, a.resolution, a.supersample, [s for s in a.only.split(",") if s] or None)
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
