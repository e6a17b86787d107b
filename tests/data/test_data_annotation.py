"""The imitation annotator: quantisation, noise rates, bias and material confusion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from physgm.data.annotation import E_CATEGORIES, NU_CATEGORIES, AnnotatorConfig, annotate, e_class, nu_class


def test_quantisation_picks_nearest_category():
    assert e_class(1e3) == 0 and e_class(4e11) == 9
    assert e_class(3e5) == 1  # log10 5.48: nearer 1e5 (5) than 1e6 (6)
    assert e_class(4e5) == 2  # log10 5.60
    assert e_class(4e10) == 7  # 7e10 is nearer in log than 1e10
    assert nu_class(0.12) == 1 and nu_class(0.13) == 2 and nu_class(0.495) == 9
    np.testing.assert_array_equal(e_class(np.array(E_CATEGORIES)), np.arange(10))
    np.testing.assert_array_equal(nu_class(np.array(NU_CATEGORIES)), np.arange(10))


def _draw(cfg: AnnotatorConfig, material: str, n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    E = 10 ** rng.uniform(3, 11.6, size=n)
    nu = rng.uniform(0.0, 0.49, size=n)
    return [annotate(material, float(e), float(v), rng, cfg) for e, v in zip(E, nu, strict=True)], E, nu


@pytest.mark.parametrize("p", [0.2, 0.35])
def test_neighbour_moves_match_configured_rate(p):
    n = 5000
    cfg = AnnotatorConfig(p_neighbour_E=p, p_neighbour_nu=p, p_material=0.0, bias_E={}, bias_nu={})
    anns, E, nu = _draw(cfg, "wood", n)
    moved_E = np.mean([a.E_class != a.E_base for a in anns])
    moved_nu = np.mean([a.nu_class != a.nu_base for a in anns])
    tol = 4 * math.sqrt(p * (1 - p) / n)  # 4 binomial standard deviations
    assert abs(moved_E - p) < tol and abs(moved_nu - p) < tol
    # Moves go to a neighbour only, and without bias the base class is the true class.
    assert all(abs(a.E_class - a.E_base) <= 1 and abs(a.nu_class - a.nu_base) <= 1 for a in anns)
    np.testing.assert_array_equal([a.E_base for a in anns], e_class(E))
    np.testing.assert_array_equal([a.nu_base for a in anns], nu_class(nu))


def test_zero_noise_gives_true_categories():
    cfg = AnnotatorConfig(p_neighbour_E=0.0, p_neighbour_nu=0.0, p_material=0.0, bias_E={}, bias_nu={})
    anns, E, nu = _draw(cfg, "stone", 500)
    np.testing.assert_array_equal([a.E_class for a in anns], e_class(E))
    assert all(a.material == "stone" for a in anns)


def test_systematic_bias_shifts_categories():
    cfg = AnnotatorConfig(
        p_neighbour_E=0.0, p_neighbour_nu=0.0, p_material=0.0, bias_E={"rubber": 2}, bias_nu={"rubber": -1}
    )
    anns, E, nu = _draw(cfg, "rubber", 500)
    np.testing.assert_array_equal([a.E_class for a in anns], np.clip(e_class(E) + 2, 0, 9))
    np.testing.assert_array_equal([a.nu_class for a in anns], np.clip(nu_class(nu) - 1, 0, 9))


def test_material_confusion_rate_and_partners():
    n, p = 4000, 0.15
    cfg = AnnotatorConfig(p_material=p, lookalikes=(("glass", "jelly"), ("glass", "plastic")))
    anns, _, _ = _draw(cfg, "glass", n)
    labels = [a.material for a in anns]
    changed = np.mean([m != "glass" for m in labels])
    assert abs(changed - p) < 4 * math.sqrt(p * (1 - p) / n)
    assert set(labels) == {"glass", "jelly", "plastic"}
    # A material without look-alikes is never confused.
    anns, _, _ = _draw(AnnotatorConfig(p_material=1.0, lookalikes=(("glass", "jelly"),)), "metal", 200)
    assert {a.material for a in anns} == {"metal"}


def test_same_rng_same_labels_and_json_values_are_categories():
    cfg = AnnotatorConfig()
    a = annotate("foam", 3e4, 0.12, np.random.default_rng(7), cfg)
    b = annotate("foam", 3e4, 0.12, np.random.default_rng(7), cfg)
    assert a == b
    j = a.to_json()
    assert j["E"] in E_CATEGORIES and j["nu"] in NU_CATEGORIES


def test_bad_config_is_rejected():
    with pytest.raises(ValueError, match="p_neighbour_E"):
        AnnotatorConfig(p_neighbour_E=1.5)
    with pytest.raises(ValueError, match="unknown annotator settings"):
        AnnotatorConfig.from_dict({"p_neighbor": 0.1})
