"""The real-object evaluation set: its table, its build command, and the MJCF assembler under it."""

from __future__ import annotations

import numpy as np
import pytest

from physgm.data import mjcf
from physgm.data.check import check_asset
from physgm.data.format import load_asset, read_split
from physgm.data.real_objects import OBJECTS, load_object, main, package_root
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
