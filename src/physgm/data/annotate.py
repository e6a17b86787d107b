"""Label assets' materials with the semantic prior, the way PhysAssets was labelled by an annotator.

    python -m physgm.data.annotate ROOT [--views N] [--overwrite] [--top K] [--min-mass P]

For every asset folder under ROOT (or ROOT itself when it is one), the frozen ImageNet
MobileNetV2 classifies a few views (default: the 4-view input set at elevation 0, the views the
model sees), composited over white and resized to 224 px; the logits are averaged over views and
folded onto the material table by ``physgm.model.semantic_prior``. The material's default E and
nu from the material table, quantised to the annotation categories, complete the label, which
is written as ``annotation`` into ``physical.json`` (temporary file + rename, so a crash never
leaves half a file). An existing annotation is kept unless ``--overwrite``. Prints one JSON
summary; exit code 1 when an asset could not be read.

An asset that gains an ``annotation`` is read as "top-level values are the truth, the annotation
is the training label" (``physgm.data.format.parse_physical``): for an imported mesh the
top-level material is then the hand label and the annotation this prior's guess.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from physgm.data.annotation import E_CATEGORIES, NU_CATEGORIES, e_class, nu_class
from physgm.data.format import AssetError, load_asset
from physgm.data.views import NUM_INPUT_SET, ViewConfig, select_views
from physgm.data.writer import TMP_PREFIX, write_json
from physgm.model.semantic_prior import imagenet_logits, material_prior, pool_views, top_classes
from physgm.physics.materials import MATERIAL_NAMES, get_material

SOURCE = "imagenet-mobilenet_v2 semantic prior"
BACKGROUND = 1.0  # views are composited over white, as the model's inputs are


@dataclass
class SemanticAnnotation:
    """The annotator's label for one asset (E and nu are category values, docs/data.md)."""

    material: str
    E: float  # Pa, one of E_CATEGORIES: the material's default E, quantised
    nu: float  # one of NU_CATEGORIES
    material_probability: float  # p(material | views) under the prior
    mass: float  # probability of ImageNet classes that map to any material
    views: list[int]  # view indices classified
    top: list[tuple[int, str, float]]  # most probable ImageNet classes (index, name, p)

    def to_json(self) -> dict:
        return {
            "material": self.material,
            "E": self.E,
            "nu": self.nu,
            "E_class": E_CATEGORIES.index(self.E),
            "nu_class": NU_CATEGORIES.index(self.nu),
            "source": SOURCE,
            "material_probability": round(self.material_probability, 4),
            "mass": round(self.mass, 4),
            "views": self.views,
            "imagenet_top": [{"index": i, "name": n, "p": round(p, 4)} for i, n, p in self.top],
        }


def asset_folders(root: Path) -> list[Path]:
    """Asset folders (those holding physical.json) under ``root``, or ``root`` itself if it is one."""
    if not root.is_dir():
        raise FileNotFoundError(f"{root} is not a directory; give the folder that holds the asset folders")
    if (root / "physical.json").is_file():
        return [root]
    found = sorted(
        p
        for p in root.iterdir()
        if p.is_dir() and not p.name.startswith(".") and (p / "physical.json").is_file()
    )
    if not found:
        raise FileNotFoundError(
            f"no assets under {root}: expected folders <asset_id>/ with physical.json, cameras.json and "
            "rgba/ views (docs/data.md); make them with python -m physgm.data.from_meshes or "
            "physgm.data.synth"
        )
    return found


def annotation_views(c2w: torch.Tensor, n: int) -> list[int]:  # c2w [C, 4, 4]
    """The first ``n`` views of the model's input set (elevation 0, azimuth 0, +90, ...), then the others."""
    count = c2w.shape[0]
    if not 1 <= n <= count:
        raise ValueError(f"--views must be between 1 and the asset's {count} views, got {n}")
    if count < NUM_INPUT_SET:
        return list(range(n))
    inputs, _ = select_views(c2w, ViewConfig(num_targets=NUM_INPUT_SET), rng=None)
    return (inputs + [i for i in range(count) if i not in inputs])[:n]


def label_material(
    material: str, probability: float, mass: float, views: list[int], top
) -> SemanticAnnotation:
    """A label with the material table's default E and nu, on the annotation categories."""
    m = get_material(material)
    E = E_CATEGORIES[int(e_class(m.E))]
    nu = NU_CATEGORIES[int(nu_class(m.nu))]
    return SemanticAnnotation(material, E, nu, probability, mass, views, top)


def annotate_asset(
    path: Path, net: nn.Module, views: int = NUM_INPUT_SET, top: int = 5
) -> SemanticAnnotation:
    """Classify an asset's views and fold their mixture (``pool_views``) onto the material table."""
    asset = load_asset(path)
    picks = annotation_views(asset.cameras.c2w, views)
    rgba = torch.from_numpy(np.ascontiguousarray(asset.load_rgba(picks))).permute(0, 3, 1, 2)  # [V, 4, H, W]
    alpha = rgba[:, 3:]
    rgb = rgba[:, :3] * alpha + BACKGROUND * (1 - alpha)  # straight alpha over white
    logits = pool_views(imagenet_logits(net, rgb, BACKGROUND), dim=0)  # [1000]
    probs, mass = material_prior(logits)
    best = int(probs.argmax())
    return label_material(
        MATERIAL_NAMES[best], float(probs[best]), float(mass), picks, top_classes(logits, top)
    )


def write_annotation(path: Path, annotation: SemanticAnnotation) -> None:
    """Set ``annotation`` in ``path/physical.json``, keeping every other key, atomically."""
    physical_path = path / "physical.json"
    physical = json.loads(physical_path.read_text())
    physical["annotation"] = annotation.to_json()
    tmp = path / f"{TMP_PREFIX}physical.json"
    try:
        write_json(tmp, physical)
        os.replace(tmp, physical_path)  # atomic on POSIX: readers see the old or the new file
    finally:
        tmp.unlink(missing_ok=True)


def has_annotation(path: Path) -> bool:
    return "annotation" in json.loads((path / "physical.json").read_text())


def annotate_root(
    root: str | os.PathLike,
    net: nn.Module | None = None,
    views: int = NUM_INPUT_SET,
    overwrite: bool = False,
    top: int = 5,
    min_mass: float = 0.0,
) -> dict:
    """Annotate every asset under ``root``; returns the summary that the command prints.

    Args:
        net: the ImageNet classifier; default ``load_mobilenet_v2()``.
        min_mass: assets whose mapped-class probability is below this are left unlabelled
            (the classifier sees no object the table knows).
    """
    if views < 1:
        raise ValueError(f"views must be at least 1, got {views}")
    folders = asset_folders(Path(root))
    summary: dict = {"root": str(root), "assets": len(folders), "annotated": 0, "kept_existing": 0}
    summary.update({"below_min_mass": 0, "failed": 0, "materials": {}, "labels": {}, "failures": {}})
    materials: Counter[str] = Counter()
    for folder in folders:
        try:
            keep = not overwrite and has_annotation(folder)
        except (ValueError, OSError) as err:  # unreadable physical.json
            summary["failed"] += 1
            summary["failures"][folder.name] = f"physical.json: {err}"
            continue
        if keep:
            summary["kept_existing"] += 1
            continue
        if net is None:  # loaded once an asset needs it; a missing weights package stops the run
            from physgm.model.pretrained import load_mobilenet_v2

            net = load_mobilenet_v2()
        try:
            ann = annotate_asset(folder, net, views, top)
        except (AssetError, ValueError, OSError) as err:  # malformed asset or undecodable views
            summary["failed"] += 1
            summary["failures"][folder.name] = str(err)
            continue
        label = {
            "material": ann.material,
            "p": round(ann.material_probability, 3),
            "mass": round(ann.mass, 3),
            "top": ann.top[0][1],
        }
        if ann.mass < min_mass:
            summary["below_min_mass"] += 1
            summary["labels"][folder.name] = {**label, "written": False}
            continue
        write_annotation(folder, ann)
        summary["annotated"] += 1
        materials[ann.material] += 1
        summary["labels"][folder.name] = label
    summary["materials"] = dict(sorted(materials.items()))
    return summary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m physgm.data.annotate",
        description="Write a semantic-prior material annotation into each asset's physical.json.",
    )
    p.add_argument("root", type=Path, help="folder of asset folders (or one asset folder)")
    p.add_argument(
        "--views", type=int, default=NUM_INPUT_SET, help="views to classify per asset (input set first)"
    )
    p.add_argument(
        "--overwrite", action="store_true", help="replace existing annotations (default: keep them)"
    )
    p.add_argument("--top", type=int, default=5, help="ImageNet classes stored with each annotation")
    p.add_argument(
        "--min-mass",
        type=float,
        default=0.0,
        help="leave assets unlabelled below this mapped-class probability",
    )
    a = p.parse_args(argv)
    try:
        summary = annotate_root(a.root, views=a.views, overwrite=a.overwrite, top=a.top, min_mass=a.min_mass)
    except (FileNotFoundError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(json.dumps(summary, indent=1))
    return 1 if summary["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
