"""Semantic material prior: the frozen ImageNet classifier's belief, folded onto the material table.

``conf/semantic/imagenet_materials.yaml`` gives each of the 1000 ImageNet classes one material of
``MATERIAL_NAMES`` or ``none`` (animals, scenes, plants...). For an image with classifier logits
``l`` and class probabilities ``q = softmax(l / T)``:

    mass      = sum of q over classes mapped to any material       (is it a known object at all?)
    p(m | x)  = sum of q over classes mapped to m, divided by mass  (which material, if it is)

This is the offline stand-in for the paper's vision-language annotator (issue 21, item 3): it
labels real imagery (``python -m physgm.data.annotate``) and can be fused with the physics head.
Shape letters: B batch, M materials (15).

    python -m physgm.model.photo_prior IMAGE [IMAGE ...]   # zero-shot material of photos, JSON
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import torch
import torch.nn.functional as F
import yaml
from torch import Tensor, nn

from physgm.model.pretrained import CLASSIFIER_SIZE, IMAGENET_MEAN, IMAGENET_STD
from physgm.physics.materials import MATERIAL_NAMES
from physgm.resources import conf_dir

NONE = "none"  # the table's name for "no material of the table"
NUM_CLASSES = 1000


def semantic_table_path() -> Path:
    """Where the class -> material table lives: ``conf/semantic/`` of the package's config tree
    (``physgm.resources``, so an installed wheel finds it too)."""
    return conf_dir() / "semantic" / "imagenet_materials.yaml"


@dataclass(frozen=True)
class MaterialGroup:
    """One group of the table: classes that share a material, and why."""

    material: str | None  # a name of MATERIAL_NAMES, or None for the table's `none`
    reason: str
    classes: dict[int, str]  # ImageNet index -> class name


@dataclass(frozen=True)
class SemanticTable:
    """The validated table."""

    groups: tuple[MaterialGroup, ...]
    materials: tuple[str | None, ...]  # [1000] material of each ImageNet class, None for none


def _fail(path: Path, message: str) -> None:
    raise ValueError(f"semantic material table {path}: {message}")


def _parse_group(raw: object, g: int, path: Path) -> MaterialGroup:
    if not isinstance(raw, dict) or not {"material", "reason", "classes"} <= set(raw):
        _fail(path, f"group {g} must be a mapping with keys material, reason, classes; got {raw!r:.120}")
    material = raw["material"]
    if material != NONE and material not in MATERIAL_NAMES:
        _fail(
            path,
            f"group {g} names unknown material {material!r}; "
            f"use one of {', '.join(MATERIAL_NAMES)} or {NONE}",
        )
    if not isinstance(raw["reason"], str) or not raw["reason"].strip():
        _fail(
            path, f"group {g} ({material}) has no reason; say in a few words why these classes are {material}"
        )
    classes = raw["classes"]
    if not isinstance(classes, dict) or not classes:
        _fail(path, f"group {g} ({material}): classes must be a non-empty mapping `index: name`")
    for index, name in classes.items():
        if not isinstance(index, int) or not 0 <= index < NUM_CLASSES:
            _fail(
                path,
                f"group {g} ({material}): class key {index!r} ({name}) is not an index in "
                f"0..{NUM_CLASSES - 1}",
            )
    return MaterialGroup(None if material == NONE else material, raw["reason"].strip(), dict(classes))


def load_semantic_table(path: str | Path | None = None, categories: list[str] | None = None) -> SemanticTable:
    """Read and validate a class -> material table.

    Every ImageNet class must appear exactly once, under its own name (so an index typo cannot
    silently move a class), and every material must be a table name or ``none``.

    Args:
        path: the YAML file; default ``semantic_table_path()``.
        categories: the 1000 class names in classifier order; default torchvision's list, as shipped
            in conf/semantic/imagenet_classes.txt (``pretrained.imagenet_categories``).
    """
    path = Path(path) if path is not None else semantic_table_path()
    if not path.is_file():
        raise FileNotFoundError(
            f"semantic material table {path} not found (conf/semantic/imagenet_materials.yaml)"
        )
    if categories is None:
        from physgm.model.pretrained import imagenet_categories

        categories = imagenet_categories()
    raw = yaml.safe_load(path.read_text())
    if not isinstance(raw, dict) or not isinstance(raw.get("groups"), list):
        _fail(path, "must hold a mapping with a list `groups:` of {material, reason, classes}")
    groups = tuple(_parse_group(r, g, path) for g, r in enumerate(raw["groups"]))
    seen: dict[int, str | None] = {}
    for grp in groups:
        here = grp.material or NONE
        for index, name in grp.classes.items():
            if str(name) != categories[index]:
                _fail(
                    path,
                    f"class {index} is {categories[index]!r} in ImageNet but the table ({here}) calls "
                    f"it {name!r}",
                )
            if index in seen:
                _fail(
                    path,
                    f"class {index} ({categories[index]}) appears twice: under {seen[index] or NONE} "
                    f"and {here}",
                )
            seen[index] = grp.material
    missing = [i for i in range(NUM_CLASSES) if i not in seen]
    if missing:
        listing = ", ".join(f"{i} ({categories[i]})" for i in missing[:10])
        _fail(
            path, f"{len(missing)} classes are missing, e.g. {listing}; add each under a material or {NONE}"
        )
    return SemanticTable(groups, tuple(seen[i] for i in range(NUM_CLASSES)))


@cache
def _default_table() -> SemanticTable:
    return load_semantic_table()


def class_materials() -> list[str | None]:
    """Material name of each ImageNet class in classifier order ([1000]); None where the table says none."""
    return list(_default_table().materials)


def class_to_material_matrix(materials: tuple[str | None, ...] | None = None) -> Tensor:  # [1000, M]
    """One-hot rows: entry (c, m) is 1 when class c is material m; all-zero rows for none."""
    if materials is None:
        return _default_matrix().clone()
    out = torch.zeros(len(materials), len(MATERIAL_NAMES))
    for c, m in enumerate(materials):
        if m is not None:
            out[c, MATERIAL_NAMES.index(m)] = 1.0
    return out


@cache
def _default_matrix() -> Tensor:  # [1000, M]
    return class_to_material_matrix(_default_table().materials)


def material_log_prior(
    imagenet_logits: Tensor,  # [..., 1000]
    temperature: float = 1.0,
) -> tuple[Tensor, Tensor]:  # log p(m | x) [..., M], log mass [...]
    """``material_prior`` in log space, for fusing with the physics head's log-probabilities.

    Materials no class maps to get -inf; sums run in log space, so a classifier sure the image
    shows a dog still gives a finite distribution over materials.
    """
    if not (temperature > 0 and math.isfinite(temperature)):
        raise ValueError(f"temperature must be a positive number, got {temperature}")
    if imagenet_logits.shape[-1] != NUM_CLASSES:
        raise ValueError(
            f"expected ImageNet logits [..., {NUM_CLASSES}], got shape {tuple(imagenet_logits.shape)}"
        )
    log_q = torch.log_softmax(imagenet_logits.float() / temperature, dim=-1)  # [..., 1000]
    member = _default_matrix().to(log_q.device)  # [1000, M]
    log_member = torch.where(member > 0, 0.0, -math.inf)  # [1000, M]
    log_per_material = torch.logsumexp(log_q[..., :, None] + log_member, dim=-2)  # [..., M]
    log_mass = torch.logsumexp(log_per_material, dim=-1)  # [...]
    return log_per_material - log_mass[..., None], log_mass


def material_prior(
    imagenet_logits: Tensor,  # [..., 1000] raw classifier logits
    temperature: float = 1.0,  # softens (> 1) or sharpens (< 1) the classifier before folding
) -> tuple[Tensor, Tensor]:  # probs [..., M], mass [...]
    """p(m | x): the classifier's probability of each material's classes, renormalised over mapped classes.

    Returns:
        probs: [..., M] sums to 1 over ``MATERIAL_NAMES``.
        mass: [...] total probability of the classes mapped to any material, in [0, 1]: how much
            the classifier believes the image shows an object the table knows.
    """
    log_probs, log_mass = material_log_prior(imagenet_logits, temperature)
    return log_probs.exp(), log_mass.exp()


def semantic_log_prior(
    imagenet_logits: Tensor,  # [..., 1000]
) -> Tensor:  # [..., M]
    """log p_prior(material) for fusing with the physics head: ``material_log_prior`` blended with
    uniform by the mass, log(mass * p(m | x) + (1 - mass) / M), so a classifier that sees no known
    object (an animal, a scene) gives no opinion instead of a confident one."""
    log_p, log_mass = material_log_prior(imagenet_logits)
    log_rest = torch.log1p(-log_mass.exp().clamp(max=1.0)) - math.log(log_p.shape[-1])  # [...]
    return torch.logaddexp(log_mass[..., None] + log_p, log_rest[..., None])


def pool_views(
    imagenet_logits: Tensor,  # [..., V, 1000] one object's views along ``dim``
    dim: int = -2,
) -> Tensor:  # [..., 1000] logits (log-probabilities) of the views' mixture
    """Several views of one object as one classifier output: the log of the views' mean class
    probabilities. A mixture, not a mean of logits, which multiplies the views' beliefs: there a
    view from which the object is hard to read (from behind, edge-on) vetoes the class the
    others see. On the real validation objects the mixture names the material more often
    (docs/model.md)."""
    log_q = imagenet_logits.float().log_softmax(dim=-1)
    return torch.logsumexp(log_q, dim=dim) - math.log(imagenet_logits.shape[dim])


def zero_shot_material(imagenet_logits: Tensor) -> Tensor:  # [...] int64 index into MATERIAL_NAMES
    """The most probable material under the semantic prior."""
    return material_log_prior(imagenet_logits)[0].argmax(dim=-1)


def classifier_input(
    rgb: Tensor,  # [B, 3, H, W] in [0, 1], already composited over the background
    background: float = 1.0,
    size: int = CLASSIFIER_SIZE,
) -> Tensor:  # [B, 3, size, size] ImageNet-normalised
    """Pad to a square with the background (the whole object stays in view, undistorted), resize,
    normalise."""
    h, w = rgb.shape[-2:]
    side = max(h, w)
    top, left = (side - h) // 2, (side - w) // 2
    rgb = F.pad(rgb, (left, side - w - left, top, side - h - top), value=background)
    rgb = F.interpolate(rgb, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
    mean = torch.tensor(IMAGENET_MEAN, device=rgb.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=rgb.device).view(1, 3, 1, 1)
    return (rgb.clamp(0, 1) - mean) / std


@torch.no_grad()
def imagenet_logits(
    net: nn.Module,  # an ImageNet classifier in eval mode (physgm.model.pretrained.load_mobilenet_v2())
    rgb: Tensor,  # [B, 3, H, W] in [0, 1], composited over ``background``
    background: float = 1.0,
) -> Tensor:  # [B, 1000]
    """The classifier's logits for images of any size."""
    return net(classifier_input(rgb, background))


def top_classes(logits: Tensor, k: int = 3) -> list[tuple[int, str, float]]:  # logits [1000]
    """The k most probable ImageNet classes as (index, name, probability)."""
    from physgm.model.pretrained import imagenet_categories

    names = imagenet_categories()
    p, idx = torch.softmax(logits.float(), dim=-1).topk(k)
    return [(int(i), names[int(i)], float(pi)) for pi, i in zip(p, idx, strict=True)]
