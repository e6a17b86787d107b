"""``python -m physgm.model.photo_prior``: the semantic prior on photos, as a user runs it."""

import json
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_names_the_mug_ceramic_from_its_imagenet_classes_without_a_runpy_warning(run_python):
    done = run_python("-m", "physgm.model.photo_prior", str(EXAMPLES / "ceramic_mug.png"), "--top", "2")
    assert done.returncode == 0, done.stderr[-3000:]
    assert "RuntimeWarning" not in done.stderr  # the module is not imported by the package first
    (report,) = json.loads(done.stdout)
    assert report["material"] == "ceramic"
    assert report["top_classes"][0]["name"] == "coffee mug"
    assert len(report["top_classes"]) == 2
    assert 0.5 < report["material_probability"] <= 1.0 and 0.9 < report["mass"] <= 1.0
