"""The material table (conf/sim/material/*.yaml) and the validation of physics values."""

from __future__ import annotations

import math

import pytest

from physgm.physics.materials import MATERIAL_NAMES, get_material, load_material, material_table
from physgm.sim.constitutive import MODELS, MaterialParams


def test_fifteen_materials_in_the_model_order():
    assert MATERIAL_NAMES == (
        "plastic",
        "wood",
        "metal",
        "fabric",
        "ceramic",
        "stone",
        "paper",
        "leather",
        "glass",
        "rubber",
        "foam",
        "snow",
        "sand",
        "jelly",
        "plasticine",
    )
    table = material_table()
    assert list(table) == list(MATERIAL_NAMES)
    assert [get_material(n).index for n in MATERIAL_NAMES] == list(range(15))


@pytest.mark.parametrize("name", MATERIAL_NAMES)
def test_every_material_is_physical_and_cited(name):
    m = get_material(name)
    assert m.model in MODELS
    assert m.E_range[0] <= m.E <= m.E_range[1] and m.nu_range[0] <= m.nu <= m.nu_range[1] < 0.5
    limit = () if m.tensile_limit is None else ("tensile_limit",)
    for key in ("E", "nu", "density", *m.plasticity, *limit):
        assert len(m.source[key]) > 10, f"{name}: no real source for {key}"
    p = m.params()
    assert p.wave_speed() > 0 and math.isfinite(p.wave_speed())
    # Stiffer E raises the CFL speed as sqrt(E).
    assert m.params(E=4 * m.E).wave_speed() == pytest.approx(2 * p.wave_speed())


def test_expected_models_for_key_materials():
    assert get_material("sand").model == "mohr_coulomb" and get_material("sand").plasticity["cohesion"] == 0
    assert get_material("snow").model == "drucker_prager" and get_material("snow").plasticity["cohesion"] > 0
    assert get_material("metal").model == "von_mises" and get_material("plasticine").model == "von_mises"
    assert get_material("foam").model == "foam" and get_material("rubber").model == "neo_hookean"


def test_the_stiff_materials_name_the_strain_they_break_at():
    """The rigid-looking materials break (or, elastic-only, yield) within a few per cent of tension,
    metal after tens of per cent; the soft solids, plasticine and the granular ones carry none."""
    limits = {n: get_material(n).tensile_limit for n in MATERIAL_NAMES}
    assert {n for n, v in limits.items() if v is not None} == {
        "plastic",
        "wood",
        "metal",
        "ceramic",
        "stone",
        "paper",
        "glass",
    }
    assert max(limits[n] for n in ("ceramic", "stone", "glass")) <= 0.002  # brittle: about 0.1 %
    assert 0.2 <= limits["metal"] <= 0.6 and max(limits[n] for n in ("plastic", "wood", "paper")) <= 0.1


def test_unknown_material_lists_the_known_ones():
    with pytest.raises(ValueError, match="unknown material 'cheese'.*plastic, wood, metal"):
        get_material("cheese")


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(nu=0.5), "nu=0.5"),
        (dict(nu=0.7), "nu=0.7"),
        (dict(nu=-1.0), "nu=-1.0"),
        (dict(E=0.0), "E=0.0"),
        (dict(E=-3.0), "E=-3.0"),
        (dict(E=float("nan")), "E=nan"),
        (dict(density=0.0), "density=0.0"),
        (dict(density=-1.0), "density=-1.0"),
        (dict(model="goo"), "unknown constitutive model 'goo'"),
    ],
)
def test_bad_physics_values_name_the_value(kwargs, match):
    args = dict(model="fixed_corotated", E=1e6, nu=0.3, density=1000.0) | kwargs
    with pytest.raises(ValueError, match=match):
        MaterialParams(**args)


def test_model_specific_parameters_are_required():
    with pytest.raises(ValueError, match="yield_stress"):
        MaterialParams("von_mises", 1e6, 0.3, 1000.0)
    with pytest.raises(ValueError, match="friction_angle"):
        MaterialParams("drucker_prager", 1e6, 0.3, 1000.0)
    with pytest.raises(ValueError, match="cohesion=-1"):
        MaterialParams("drucker_prager", 1e6, 0.3, 1000.0, friction_angle=30.0, cohesion=-1.0)


def test_lame_parameters_and_wave_speed():
    p = MaterialParams("fixed_corotated", 2.6e6, 0.3, 1000.0)
    assert p.mu == pytest.approx(1e6)
    assert p.lam == pytest.approx(2.6e6 * 0.3 / (1.3 * 0.4))
    assert p.wave_speed() == pytest.approx(math.sqrt((p.lam + 2 * p.mu) / 1000.0))
    fluid = MaterialParams("fluid", 3e6, 0.25, 1000.0)
    assert fluid.wave_speed() == pytest.approx(math.sqrt(3e6 / (3 * 0.5) / 1000.0))


def test_a_broken_material_file_is_rejected(tmp_path):
    path = tmp_path / "rubber.yaml"
    path.write_text(  # an incompressible (nu = 0.5) rubber is out of range
        "name: rubber\nmodel: neo_hookean\ndensity: 1100\nE: 5.0e6\nnu: 0.5\nE_range: [1e6, 1e7]\n"
        "nu_range: [0.45, 0.5]\nsource: {E: 'a book on rubber', nu: 'a book on rubber', density: 'a table'}\n"
    )
    with pytest.raises(ValueError, match="nu"):
        load_material(path)
    path.write_text(
        path.read_text()
        .replace("nu: 0.5\n", "nu: 0.48\n")
        .replace("0.5]", "0.49]")
        .replace("density: 'a table'", "density: ''")
    )
    with pytest.raises(ValueError, match="no source given for \\['density'\\]"):
        load_material(path)
    fixed = path.read_text().replace("density: ''", "density: 'a table'")
    path.write_text(fixed + "tensile_limit: 5.0\n")
    with pytest.raises(ValueError, match="no source given for \\['tensile_limit'\\]"):
        load_material(path)
    path.write_text(
        fixed.replace("source: {", "source: {tensile_limit: 'a book on rubber', ") + "tensile_limit: -1\n"
    )
    with pytest.raises(ValueError, match="tensile_limit=-1.0 must be a positive strain"):
        load_material(path)
    path.write_text(
        fixed.replace("source: {", "source: {tensile_limit: 'a book on rubber', ") + "tensile_limit: 5\n"
    )
    assert load_material(path).tensile_limit == 5.0
