"""The real-object sets (evaluation and domain gate): their tables, their build command, and the
MJCF assembler under them."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from physgm.data import mjcf
from physgm.data.check import check_asset
from physgm.data.format import load_asset, read_split
from physgm.data.from_meshes import render_mesh
from physgm.data.real_object_tables import GATE_OBJECTS, OBJECTS, SEARCH_DIRS, SETS, RealObject
from physgm.data.real_objects import load_object, main, package_root
from physgm.physics.materials import MATERIAL_NAMES, get_material


def test_table_is_big_enough_labelled_and_its_files_are_installed():
    ids = [o.id for o in OBJECTS]
    assert len(ids) == len(set(ids)) and all(o.material in MATERIAL_NAMES for o in OBJECTS)
    test = [o for o in OBJECTS if o.split == "test"]
    assert len(test) >= 20 and len({o.material for o in test}) >= 5  # issue 21 item 5
    assert {o.split for o in OBJECTS} == {"val", "test"}  # nothing for training
    assert all(o.reason and (bool(o.mesh) != bool(o.xml)) for o in OBJECTS)
    for o in OBJECTS:
        root = package_root(o.source)
        for f in (o.mesh, o.xml, *o.deps, o.texture):
            assert not f or (root / f).is_file(), f"{o.id}: {f} missing from {root}"
    with pytest.raises(ModuleNotFoundError, match="scripts/setup.sh"):
        package_root("physgm_no_such_package")


@pytest.mark.parametrize("oid", ["gn_chopping_board", "gn_airplane", "gn_boat", "rs_plate_with_hole"])
def test_flat_objects_lie_flat_whatever_axis_their_file_calls_up(oid):
    # A glTF file is +y up (the board), some OBJ files too (up="y": the aircraft, the boat), others
    # +z up (the plate); each must come out with its thin axis vertical, resting as it would.
    tri = load_object(next(o for o in OBJECTS if o.id == oid)).triangles.reshape(-1, 3)
    extent = tri.max(0) - tri.min(0)
    assert extent[2] < 0.5 * extent[:2].max(), extent


def test_builds_two_objects_into_loadable_labelled_assets(tmp_path):
    out = tmp_path / "real"
    args = ["--out", str(out), "--resolution", "32", "--supersample", "1", "--only", "rs_can,mw_mug"]
    assert main(args) == 0
    assert read_split(out, "val") == ["rs_can"] and read_split(out, "test") == ["mw_mug"]
    assert read_split(out, "train") == [] and read_split(out, "dpo") == []
    for aid, material in (("rs_can", "metal"), ("mw_mug", "ceramic")):
        assert check_asset(out / aid) == []
        asset = load_asset(out / aid)
        assert len(asset) == 32 and asset.cameras.width == 32
        p = asset.physical
        assert p.material == material and not p.true_known
        assert p.E == get_material(material).E and p.extra["label_source"] == "hand"
        assert p.extra["physics_source"] == "material default" and p.extra["label_reason"]
        rgba = asset.load_rgba()  # [32, 32, 32, 4]
        coverage = rgba[..., 3].mean((1, 2))
        assert coverage.min() > 0.08 and coverage.max() < 0.8, coverage
    can = load_asset(out / "rs_can").load_rgba([0])[0]
    mug = load_asset(out / "mw_mug").load_rgba([0])[0]
    red = can[can[..., 3] > 0.99, :3].mean(0)
    assert red[0] > 1.5 * red[1], red  # the soda label's texture was found and read
    assert mug[mug[..., 3] > 0.99, :3].mean() > 0.45  # a white mug, lit: not a black blob
    with pytest.raises(ValueError, match="resolution"):
        main(["--out", str(out), "--resolution", "64", "--only", "rs_can"])


def _geometry_files(obj: RealObject) -> set[Path]:
    """The files an object's triangles come from: its mesh files, or its MJCF body file and the mesh
    files its geoms (visible or not) name."""
    root = package_root(obj.source)
    if obj.mesh:
        return {(root / f).resolve() for f in (obj.mesh, *obj.deps)}
    xml = root / obj.xml
    declared = mjcf.read_assets([root / d for d in obj.deps], [root / d for d in SEARCH_DIRS[obj.source]])
    meshes = {**declared.meshes, **mjcf.read_assets([xml], [xml.parent]).meshes}
    body = next(b for b in ET.parse(xml).getroot().iter("body") if not obj.body or b.get("name") == obj.body)
    return {xml.resolve()} | {meshes[g.get("mesh")][0] for g in body.iter("geom") if g.get("mesh")}


def test_gate_set_shares_no_object_or_geometry_file_with_the_evaluation_set():
    gate_ids = [o.id for o in GATE_OBJECTS]
    assert len(gate_ids) == len(set(gate_ids)) and not set(gate_ids) & {o.id for o in OBJECTS}
    assert 25 <= len(GATE_OBJECTS) <= 40
    assert {o.source for o in GATE_OBJECTS} == {"robosuite", "genesis", "metaworld"}
    evaluation = set().union(*(_geometry_files(o) for o in OBJECTS))
    for o in GATE_OBJECTS:
        shared = _geometry_files(o) & evaluation
        assert not shared, f"{o.id} draws from evaluation files {shared}"
    # near-copies of evaluation objects (binB ~ binA, ...) stay out too
    near = {"binB.xml", "doorlockB.xml", "shelfb.xml", "window_horiz.xml", "table_hole.xml", "boxtop.xml"}
    assert not near & {Path(o.xml).name for o in GATE_OBJECTS}


def test_gate_rows_are_labelled_installed_and_all_train_and_eval_splits_are_unchanged():
    assert all(o.material in MATERIAL_NAMES and o.reason for o in GATE_OBJECTS)
    assert all(bool(o.mesh) != bool(o.xml) for o in GATE_OBJECTS)
    for o in GATE_OBJECTS:
        root = package_root(o.source)
        for f in (o.mesh, o.xml, *o.deps, o.texture):
            assert not f or (root / f).is_file(), f"{o.id}: {f} missing from {root}"
    assert {SETS["gate"].split_of(o) for o in GATE_OBJECTS} == {"train"}
    assert SETS["eval"].objects is OBJECTS
    splits = {o.id: SETS["eval"].split_of(o) for o in OBJECTS}
    assert splits == {o.id: o.split for o in OBJECTS}
    assert all(splits[o.id] == ("test" if o.source == "metaworld" else "val") for o in OBJECTS)
    assert sum(s == "val" for s in splits.values()) == 21 and sum(s == "test" for s in splits.values()) == 22


def test_builds_a_gate_object_into_train_and_keeps_the_two_sets_apart(tmp_path):
    small = ["--resolution", "32", "--supersample", "1"]
    gate, real = tmp_path / "gate", tmp_path / "real"
    assert main(["--set", "gate", "--out", str(gate), *small, "--only", "mw_plug_wall"]) == 0
    assert read_split(gate, "train") == ["mw_plug_wall"]
    assert read_split(gate, "val") == read_split(gate, "test") == read_split(gate, "dpo") == []
    assert check_asset(gate / "mw_plug_wall") == []
    assert load_asset(gate / "mw_plug_wall").physical.material == "plastic"
    manifest = json.loads((gate / "real_objects.json").read_text())
    assert manifest["set"] == "gate" and [o["split"] for o in manifest["objects"]] == ["train"]
    with pytest.raises(ValueError, match="holds the gate set"):
        main(["--out", str(gate), *small, "--only", "rs_can"])
    with pytest.raises(ValueError, match="in the eval set: add --set"):
        main(["--set", "gate", "--out", str(tmp_path / "other"), *small, "--only", "rs_can"])

    assert main(["--out", str(real), *small, "--only", "rs_can"]) == 0
    assert json.loads((real / "real_objects.json").read_text())["set"] == "eval"
    with pytest.raises(ValueError, match="holds the eval set"):
        main(["--set", "gate", "--out", str(real), *small, "--only", "mw_plug_wall"])
    # a manifest written before there were two sets has no "set": it is the evaluation set's
    legacy = json.loads((real / "real_objects.json").read_text())
    del legacy["set"]
    (real / "real_objects.json").write_text(json.dumps(legacy))
    with pytest.raises(ValueError, match="holds the eval set"):
        main(["--set", "gate", "--out", str(real), *small, "--only", "mw_plug_wall"])
    assert not (real / "mw_plug_wall").exists()


@pytest.mark.slow
@pytest.mark.parametrize("obj", GATE_OBJECTS, ids=lambda o: o.id)
def test_every_gate_object_renders_visible_in_every_view(obj):
    rgba = render_mesh(load_object(obj), 32, 1)  # [32, 32, 32, 4]
    coverage = rgba[..., 3].mean((1, 2)) / 255
    assert coverage.min() > 0.01 and coverage.max() < 0.8, coverage


MJCF = """<mujoco>
  <compiler angle="radian"/>
  <asset><material name="red" rgba="1 0 0 1"/><material name="glass" rgba="0 0 1 0.5"/></asset>
  <default><default class="vis"><geom group="1" material="red"/></default></default>
  <worldbody>
    <body name="root" childclass="vis">
      <body name="arm" pos="1 0 0" euler="0 0 1.5707963267948966">
        <geom type="box" size=".1 .2 .3" pos=".5 0 0"/>
        <geom type="box" size=".1 .2 .3" pos=".5 0 0" group="0"/>
        <geom type="sphere" size=".05" group="4"/>
        <geom type="cylinder" size=".01" fromto="0 0 0 0 0 -.4" material="glass"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def test_mjcf_places_geoms_by_body_and_geom_frames(tmp_path):
    (tmp_path / "m.xml").write_text(MJCF)
    parts = mjcf.assemble(tmp_path / "m.xml", mjcf.Assets())
    assert [p.name for p in parts] == ["box", "cylinder"]  # the copy and the group-4 geom are left out
    box = parts[0].triangles.reshape(-1, 3)
    # pos (.5, 0, 0) turned 90 degrees about z lands at (0, .5, 0), plus the body's (1, 0, 0);
    # x and y swap extents
    np.testing.assert_allclose(box.min(0), [0.8, 0.4, -0.3], atol=1e-9)
    np.testing.assert_allclose(box.max(0), [1.2, 0.6, 0.3], atol=1e-9)
    cyl = parts[1].triangles.reshape(-1, 3)
    np.testing.assert_allclose([cyl[:, 2].min(), cyl[:, 2].max()], [-0.4, 0.0], atol=1e-9)
    np.testing.assert_allclose(parts[0].colour.factor, [1, 0, 0])  # the class's material
    # half-transparent blue over the light grey that shows through it
    np.testing.assert_allclose(parts[1].colour.factor, [0.425, 0.425, 0.925])
    quat = mjcf.frame({"quat": "0.7071067811865476 0 0 0.7071067811865476"})
    np.testing.assert_allclose(quat, mjcf.frame({"euler": "0 0 1.5707963267948966"}), atol=1e-12)
    np.testing.assert_allclose(quat, mjcf.frame({"axisangle": "0 0 1 90"}, degrees=True), atol=1e-12)
