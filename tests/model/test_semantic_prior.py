"""The ImageNet class -> material table and the semantic material prior built on it."""

from __future__ import annotations

import pytest
import torch
import yaml

from physgm.model.pretrained import imagenet_categories
from physgm.model.semantic_prior import (
    class_materials,
    class_to_material_matrix,
    classifier_input,
    load_semantic_table,
    material_log_prior,
    material_prior,
    pool_views,
    semantic_table_path,
    zero_shot_material,
)
from physgm.physics.materials import MATERIAL_NAMES

NAMES = imagenet_categories()
M = len(MATERIAL_NAMES)


def _peaked(name: str, height: float = 20.0) -> torch.Tensor:  # [1000]
    logits = torch.zeros(1000)
    logits[NAMES.index(name)] = height
    return logits


def test_table_covers_every_class_with_known_materials():
    materials = class_materials()
    assert len(materials) == 1000
    assert set(materials) <= set(MATERIAL_NAMES) | {None}
    # every material of the table can be reached from some class
    assert set(MATERIAL_NAMES) <= set(materials)
    table = load_semantic_table()
    assert sum(len(g.classes) for g in table.groups) == 1000
    assert all(g.reason for g in table.groups)


@pytest.mark.parametrize(
    ("name", "material"),
    [("coffee mug", "ceramic"), ("frying pan", "metal"), ("wok", "metal"), ("soccer ball", "leather"),
     ("wine bottle", "glass"), ("water bottle", "plastic"), ("carton", "paper"), ("teddy", "fabric"),
     ("stone wall", "stone"), ("rubber eraser", "rubber"), ("dough", "plasticine"), ("tabby", None),
     ("seashore", None)],
)  # fmt: skip
def test_spot_checks(name, material):
    assert class_materials()[NAMES.index(name)] == material


def test_matrix_is_one_hot_rows_and_zero_rows_for_none():
    W = class_to_material_matrix()
    materials = class_materials()
    assert W.shape == (1000, M)
    assert set(W.unique().tolist()) == {0.0, 1.0}
    row_sums = W.sum(1)
    assert torch.equal(row_sums, torch.tensor([0.0 if m is None else 1.0 for m in materials]))
    mug = NAMES.index("coffee mug")
    assert W[mug, MATERIAL_NAMES.index("ceramic")] == 1


def _broken(tmp_path, edit) -> str:
    raw = yaml.safe_load(semantic_table_path().read_text())
    edit(raw["groups"])
    path = tmp_path / "table.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def _group(groups, material):
    return next(g for g in groups if g["material"] == material)


def test_broken_tables_give_errors_naming_the_class(tmp_path):
    def rename(groups):
        _group(groups, "ceramic")["classes"][504] = "cofee mug"

    with pytest.raises(ValueError, match=r"class 504 is 'coffee mug' in ImageNet.*'cofee mug'"):
        load_semantic_table(_broken(tmp_path, rename))

    def drop(groups):
        del _group(groups, "metal")["classes"][567]

    with pytest.raises(ValueError, match=r"1 classes are missing, e.g. 567 \(frying pan\)"):
        load_semantic_table(_broken(tmp_path, drop))

    def duplicate(groups):
        _group(groups, "glass")["classes"][504] = "coffee mug"

    with pytest.raises(
        ValueError,
        match=r"class 504 \(coffee mug\) appears twice: under (ceramic and glass|glass and ceramic)",
    ):
        load_semantic_table(_broken(tmp_path, duplicate))

    def unknown(groups):
        _group(groups, "wood")["material"] = "timber"

    with pytest.raises(ValueError, match=r"unknown material 'timber'"):
        load_semantic_table(_broken(tmp_path, unknown))


def test_prior_sums_to_one_and_finds_ceramic_for_a_mug():
    probs, mass = material_prior(_peaked("coffee mug"))
    assert probs.shape == (M,) and mass.shape == ()
    torch.testing.assert_close(probs.sum(), torch.tensor(1.0))
    assert probs[MATERIAL_NAMES.index("ceramic")] > 0.99
    assert mass > 0.99
    assert int(zero_shot_material(_peaked("coffee mug"))) == MATERIAL_NAMES.index("ceramic")


def test_prior_matches_the_plain_definition_on_random_batches():
    logits = 3 * torch.randn(2, 3, 1000, generator=torch.Generator().manual_seed(0))
    probs, mass = material_prior(logits, temperature=1.5)
    assert probs.shape == (2, 3, M) and mass.shape == (2, 3)
    q = torch.softmax(logits / 1.5, dim=-1)
    per_material = q @ class_to_material_matrix()  # [2, 3, M]
    torch.testing.assert_close(mass, per_material.sum(-1))
    torch.testing.assert_close(probs, per_material / per_material.sum(-1, keepdim=True))
    labels = zero_shot_material(logits)
    assert labels.dtype == torch.int64 and labels.shape == (2, 3)
    assert torch.equal(labels, (torch.softmax(logits, -1) @ class_to_material_matrix()).argmax(-1))


def test_views_pool_into_the_mixture_of_their_class_probabilities():
    logits = 4 * torch.randn(2, 3, 1000, generator=torch.Generator().manual_seed(1))  # [B, V, 1000]
    pooled = pool_views(logits, dim=1)
    torch.testing.assert_close(pooled.exp(), torch.softmax(logits, -1).mean(1))
    torch.testing.assert_close(pool_views(logits[:, :1], dim=1), logits[:, 0].log_softmax(-1))  # one view
    # A mug seen clearly once and three times from where it reads as nothing in particular (the mug
    # class ruled out, a gong a little likelier than the rest) is still a ceramic mug. A mean of the
    # logits is a product of the views' beliefs: any view that rules the mug out vetoes it.
    mug, other = _peaked("coffee mug"), torch.zeros(1000)
    other[imagenet_categories().index("gong")] = 4.0
    other[imagenet_categories().index("coffee mug")] = -20.0
    views = torch.stack([mug, other, other, other])
    assert int(zero_shot_material(pool_views(views, dim=0))) == MATERIAL_NAMES.index("ceramic")
    assert int(zero_shot_material(views.mean(0))) != MATERIAL_NAMES.index("ceramic")


def test_a_classifier_temperature_that_is_not_positive_is_refused():
    from physgm.model.config import PhysGMConfig
    from physgm.model.physgm import PhysGM

    with pytest.raises(ValueError, match="semantic_prior_temperature must be > 0"):
        PhysGM(PhysGMConfig.from_dict({"physics_head": {"semantic_prior_temperature": 0.0}}))


def test_mass_is_the_share_of_mapped_classes():
    # flat logits: every class equally likely, so the mass is the fraction of classes with a material
    mapped = sum(m is not None for m in class_materials())
    _, mass = material_prior(torch.zeros(1000))
    torch.testing.assert_close(mass, torch.tensor(mapped / 1000))
    # a confident "tabby cat" leaves almost no mass, yet a finite distribution over materials
    probs, mass = material_prior(_peaked("tabby", 40.0))
    assert mass < 1e-12
    assert torch.isfinite(probs).all()
    torch.testing.assert_close(probs.sum(), torch.tensor(1.0))
    log_probs, log_mass = material_log_prior(_peaked("tabby", 200.0))
    assert torch.isfinite(log_mass) and log_mass < -100  # mass underflows in float32, its log does not
    assert torch.isfinite(log_probs.logsumexp(-1))


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError, match="temperature"):
        material_prior(torch.zeros(1000), temperature=0.0)
    with pytest.raises(ValueError, match=r"\[\.\.\., 1000\]"):
        material_prior(torch.zeros(10))


def test_classifier_input_pads_with_background_and_normalises():
    rgb = torch.zeros(1, 3, 10, 20)  # black, twice as wide as tall
    x = classifier_input(rgb, background=1.0)
    assert x.shape == (1, 3, 224, 224)
    mean = torch.tensor((0.485, 0.456, 0.406)).view(3, 1)
    std = torch.tensor((0.229, 0.224, 0.225)).view(3, 1)
    torch.testing.assert_close(x[0, :, 0, :], ((1 - mean) / std).expand(3, 224))  # white padding on top
    torch.testing.assert_close(x[0, :, 112, :], ((0 - mean) / std).expand(3, 224))  # the image in the middle


def test_material_temperature_softens_the_fused_distribution_and_keeps_its_mode():
    from physgm.model.config import PhysGMConfig
    from physgm.model.physgm import PhysGM
    from physgm.model.physics_head import fuse_material_logits

    gen = torch.Generator().manual_seed(0)
    head, prior = torch.randn(3, 15, generator=gen), torch.randn(3, 15, generator=gen).log_softmax(-1)
    fused = fuse_material_logits(head, prior, 2.0)
    tempered = fuse_material_logits(head, prior, 2.0, temperature=2.0)
    # (p_head * p_prior^2)^(1/2), renormalised: the square root of the fused probabilities, rescaled
    expected = fused.softmax(-1).sqrt() / fused.softmax(-1).sqrt().sum(-1, keepdim=True)
    torch.testing.assert_close(tempered.softmax(-1), expected)
    assert torch.equal(tempered.argmax(-1), fused.argmax(-1))
    torch.testing.assert_close(fuse_material_logits(head, None, 0.0, 4.0), head / 4)
    with pytest.raises(ValueError, match="material_temperature must be > 0"):
        PhysGM(PhysGMConfig.from_dict({"physics_head": {"material_temperature": -1.0}}))
