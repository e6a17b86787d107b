"""The shipped examples through ``simulate.py``'s physics choice: is each one's behaviour class right?

    python -m physgm.train.evaluate_examples CKPT [--examples examples] [--prior-sweep 0,2,8]

``examples/labels.json`` gives each example input (a picture or a folder of posed views) its
material. For each, the model predicts the physics posterior as ``simulate.py`` does
(``prepare_input``, ``predict_scene``) and ``choose_physics`` picks the run ``simulate.py``
would simulate first (the posterior mean). An example scores when that material's behaviour
class (rigid, soft elastic, plastic, granular, fluid, foam) is its label's. With
``--prior-sweep`` the same runs at other weights w of the semantic prior (the checkpoint's own w
first). One JSON object goes to stdout; a line per example to stderr.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from physgm.errors import UserError
from physgm.model.checkpoint import input_size, load_model
from physgm.model.predict import predict_scene
from physgm.physics.behaviour import MATERIAL_BEHAVIOUR
from physgm.pipeline.config import PhysicsOverrides
from physgm.pipeline.physics_choice import choose_physics
from physgm.pipeline.prepared_input import prepare_input

LABELS_FILE = "labels.json"


def read_labels(folder: Path) -> dict[str, str]:
    """``labels.json`` of an examples folder: input name -> material of the table."""
    path = folder / LABELS_FILE
    if not path.is_file():
        raise UserError(f"{path} not found: it maps each example input to its material")
    try:
        labels = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise UserError(f"{path} is not valid JSON ({err}); it maps each input name to a material") from None
    if not isinstance(labels, dict):
        raise UserError(f"{path} must hold one object mapping each input name to a material")
    unknown = {k: v for k, v in labels.items() if v not in MATERIAL_BEHAVIOUR}
    missing = [k for k in labels if not (folder / k).exists()]
    if unknown or missing:
        raise UserError(f"{path}: materials not in the table {unknown}, inputs not in {folder}: {missing}")
    return labels


def evaluate_examples(model, size: int, folder: Path, weights: list[float], log=print) -> dict:
    """Per example and per w: the chosen material and whether its behaviour class is right."""
    labels = read_labels(folder)
    head = model.config.physics_head
    own = head.semantic_prior_weight
    rows, right = [], dict.fromkeys(weights, 0)
    try:
        for name, truth in labels.items():
            inp = prepare_input(folder / name, size)
            chosen, real = {}, None
            for w in weights:
                head.semantic_prior_weight = w
                pred = predict_scene(model, inp.images, inp.masks, inp.c2w, inp.Ks, inp.classifier_images)
                real = pred.domain_real  # how real the views look to the gate: the real expert's weight
                material = choose_physics(pred.posterior, PhysicsOverrides(), seed=0)[0].material
                ok = MATERIAL_BEHAVIOUR[material] == MATERIAL_BEHAVIOUR[truth]
                right[w] += ok
                chosen[f"{w:g}"] = {"material": material, "behaviour_right": ok}
            row = {"input": name, "label": truth, "by_prior_weight": chosen}
            if real is not None:
                row["domain_gate"] = round(real, 3)
            rows.append(row)
            gate = f" gate={row['domain_gate']:.2f}" if "domain_gate" in row else ""
            picks = " ".join(f"w={w}: {c['material']}" for w, c in chosen.items())
            log(f"{name:26s} {truth:10s}{gate} {picks}")
    finally:
        head.semantic_prior_weight = own
    return {
        "examples": len(labels),
        "right_behaviour": {f"{w:g}": right[w] for w in weights},
        "rows": rows,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m physgm.train.evaluate_examples", description=__doc__.split("\n")[0]
    )
    p.add_argument("ckpt", type=Path)
    p.add_argument("--examples", type=Path, default=Path("examples"), help="folder with labels.json")
    p.add_argument("--prior-sweep", default="", help="comma-separated w values to also score")
    a = p.parse_args(argv)
    if not a.ckpt.is_file():
        raise SystemExit(f"checkpoint {a.ckpt} not found")
    try:
        model, ckpt = load_model(a.ckpt)
        weights = [model.config.physics_head.semantic_prior_weight]
        weights += [float(w) for w in a.prior_sweep.split(",") if w and float(w) not in weights]
        result = evaluate_examples(
            model, input_size(model, ckpt.hparams), a.examples, weights, lambda s: print(s, file=sys.stderr)
        )
    except UserError as err:
        raise SystemExit(f"error: {err}") from None
    print(json.dumps({"ckpt": str(a.ckpt), **result}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
