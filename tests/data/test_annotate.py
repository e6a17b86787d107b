"""python -m physgm.data.annotate: semantic-prior labels written into physical.json."""

from __future__ import annotations

import json
import shutil

import pytest
import torch
from torch import nn

from physgm.data.annotate import SOURCE, annotate_root, annotation_views, main
from physgm.data.format import load_asset
from physgm.data.synth import generate
from physgm.model.pretrained import imagenet_categories

MUG = imagenet_categories().index("coffee mug")


class MugClassifier(nn.Module):
    """Stands in for MobileNetV2: always very sure it sees a coffee mug; records its inputs."""

    def __init__(self) -> None:
        super().__init__()
        self.inputs: list[torch.Tensor] = []

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [B, 3, 224, 224] -> [B, 1000]
        self.inputs.append(x)
        logits = torch.zeros(x.shape[0], 1000)
        logits[:, MUG] = 20.0
        return logits


@pytest.fixture(scope="module")
def two_assets(tmp_path_factory, make_config):
    root = tmp_path_factory.mktemp("annotate") / "synthetic"
    summary = generate(make_config(2, seed=5), root, workers=1, progress=False)
    assert summary["done"] == 2, summary["failures"]
    return root


@pytest.fixture
def real_like(two_assets, tmp_path):
    """A copy of the two assets with their annotation removed, as imported meshes have none."""
    root = tmp_path / "real"
    shutil.copytree(two_assets, root)
    for physical in root.glob("*/physical.json"):
        d = json.loads(physical.read_text())
        del d["annotation"]
        physical.write_text(json.dumps(d))
    return root


def _physical(root, asset="syn_000000") -> dict:
    return json.loads((root / asset / "physical.json").read_text())


def test_writes_the_annotation_with_quantised_table_defaults(real_like):
    before = _physical(real_like)
    net = MugClassifier()
    summary = annotate_root(real_like, net=net, top=3)
    assert summary["annotated"] == 2 and summary["failed"] == 0
    assert summary["materials"] == {"ceramic": 2}
    # the 4 input views of each asset, composited over white and resized for the classifier
    assert [x.shape for x in net.inputs] == [(4, 3, 224, 224)] * 2
    after = _physical(real_like)
    ann = after.pop("annotation")
    assert after == before  # every other key kept
    assert ann["material"] == "ceramic" and ann["source"] == SOURCE
    assert ann["E"] == 7e10 and ann["nu"] == 0.2  # ceramic's 7e10 Pa and 0.22 on the category grid
    assert (ann["E_class"], ann["nu_class"]) == (7, 3)
    assert ann["views"] == [0, 2, 4, 6]
    assert ann["imagenet_top"][0] == {"index": MUG, "name": "coffee mug", "p": 1.0}
    assert len(ann["imagenet_top"]) == 3
    assert ann["material_probability"] == 1.0 and ann["mass"] == 1.0
    asset = load_asset(real_like / "syn_000000")  # the format reads it back
    assert asset.physical.annotation.material == "ceramic" and asset.physical.annotation.E == 7e10
    assert not list(real_like.glob("*/.tmp-*"))  # no temporary file left behind


def test_existing_annotations_are_kept_unless_overwrite(real_like):
    annotate_root(real_like, net=MugClassifier())
    ours = (real_like / "syn_000000" / "physical.json").read_bytes()
    # a hand label in place: a second run must not touch it
    hand = _physical(real_like, "syn_000001")
    hand["annotation"] = {"material": "metal", "E": 2e11, "nu": 0.3, "E_class": 8, "nu_class": 5}
    (real_like / "syn_000001" / "physical.json").write_text(json.dumps(hand))
    summary = annotate_root(real_like, net=MugClassifier())
    assert summary["kept_existing"] == 2 and summary["annotated"] == 0
    assert (real_like / "syn_000000" / "physical.json").read_bytes() == ours
    assert _physical(real_like, "syn_000001")["annotation"]["material"] == "metal"
    summary = annotate_root(real_like, net=MugClassifier(), overwrite=True)
    assert summary["annotated"] == 2
    assert _physical(real_like, "syn_000001")["annotation"]["material"] == "ceramic"


def test_views_and_min_mass(real_like):
    net = MugClassifier()
    annotate_root(real_like, net=net, views=2)
    assert [x.shape[0] for x in net.inputs] == [2, 2]
    assert _physical(real_like)["annotation"]["views"] == [0, 2]
    c2w = load_asset(real_like / "syn_000000").cameras.c2w
    assert annotation_views(c2w, 6) == [0, 2, 4, 6, 1, 3]
    with pytest.raises(ValueError, match="between 1 and the asset's 32 views"):
        annotation_views(c2w, 33)

    class Cat(MugClassifier):  # sure it sees a cat: no class of the table
        def forward(self, x):
            return torch.zeros(x.shape[0], 1000).index_fill_(1, torch.tensor([281]), 30.0)

    summary = annotate_root(real_like, net=Cat(), overwrite=True, min_mass=0.5)
    assert summary["below_min_mass"] == 2 and summary["annotated"] == 0
    assert _physical(real_like)["annotation"]["views"] == [0, 2]  # the earlier label stays


def test_real_classifier_labels_an_asset(real_like, capsys):
    # the shipped MobileNetV2 end to end through the command line, on one asset folder
    assert main([str(real_like / "syn_000000"), "--top", "2"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["annotated"] == 1
    ann = _physical(real_like)["annotation"]
    assert ann["material"] in summary["materials"] and len(ann["imagenet_top"]) == 2
    assert 0.0 < ann["mass"] <= 1.0 and 0.0 < ann["material_probability"] <= 1.0
    load_asset(real_like / "syn_000000")


def test_root_without_assets_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no assets under"):
        annotate_root(tmp_path / "empty", net=MugClassifier())
    assert main([str(tmp_path / "empty")]) == 2
    assert "no assets under" in capsys.readouterr().err
    assert main([str(tmp_path / "missing")]) == 2


def test_malformed_asset_is_reported_and_the_rest_annotated(real_like, capsys):
    (real_like / "syn_000001" / "cameras.json").write_text("{}")
    summary = annotate_root(real_like, net=MugClassifier())
    assert summary["annotated"] == 1 and summary["failed"] == 1
    assert "syn_000001" in summary["failures"] and "frames" in summary["failures"]["syn_000001"]
