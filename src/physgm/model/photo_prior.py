"""The semantic prior's zero-shot material of photos, as JSON (``physgm.model.semantic_prior``).

    python -m physgm.model.photo_prior IMAGE [IMAGE ...] [--top K]

Its own module, not a ``__main__`` of ``semantic_prior``: the model package imports that one, and
running an already-imported module with ``-m`` makes Python warn.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from physgm.model.semantic_prior import imagenet_logits, material_prior, top_classes
from physgm.physics.materials import MATERIAL_NAMES


def main(argv: list[str] | None = None) -> int:
    """Print, for each photo, its top ImageNet classes and the semantic prior's material (JSON)."""
    from physgm.inputs import load_photo
    from physgm.model.pretrained import load_mobilenet_v2

    p = argparse.ArgumentParser(prog="python -m physgm.model.photo_prior", description=main.__doc__)
    p.add_argument("images", nargs="+", type=Path, help="PNG or JPEG photos; RGBA is composited over white")
    p.add_argument("--top", type=int, default=3, help="ImageNet classes to list per photo")
    a = p.parse_args(argv)
    net = load_mobilenet_v2()
    report = []
    for path in a.images:
        photo = load_photo(path)
        rgb = torch.from_numpy(photo.rgb).permute(2, 0, 1)[None]  # [1, 3, H, W]
        if photo.alpha is not None:
            alpha = torch.from_numpy(photo.alpha)[None, None]
            rgb = rgb * alpha + (1 - alpha)
        logits = imagenet_logits(net, rgb)[0]
        probs, mass = material_prior(logits)
        m = int(probs.argmax())
        report.append(
            {
                "image": str(path),
                "material": MATERIAL_NAMES[m],
                "material_probability": round(float(probs[m]), 4),
                "mass": round(float(mass), 4),
                "top_classes": [
                    {"index": i, "name": n, "p": round(q, 4)} for i, n, q in top_classes(logits, a.top)
                ],
            }
        )
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
