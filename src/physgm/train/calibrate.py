"""Calibrate a checkpoint's physics posterior on a validation split, for ``physgm.train.export``.

    python -m physgm.train.calibrate CKPT --data ROOT [ROOT ...] [--split val] [--level 0.9]
        [--prior-weight W]

Runs the model on each asset of the split that has true physics, once with 1 and once with 4 input
views (the fixed views ``physgm.train.evaluate`` uses), and chooses three numbers of the physics head:

- ``nu_logvar_offset``: the log-variance offset whose ``level`` interval of nu covers that share of the
  assets at each view count (the larger of the two counts' quantile offsets).
- ``E_logvar_offset`` and ``material_temperature``. With ``physics_head.E_frame="material"`` the
  posterior of log10 E is a mixture over materials, so what its central interval covers depends on
  how much weight the other materials get (the temperature T of the material logits) as well as on
  each Gaussian's width (the offset). Every pair on a grid is scored; among the pairs whose interval
  covers at least ``level`` at each view count, the one with the lowest mean negative log density of
  the true log10 E (a proper score, so the sharpest posterior that is still right) is kept. If none
  reaches ``level``, the pair of highest coverage. A global-frame E does not depend on the material,
  so its T stays 1.

Offsets and the temperature are totals (the checkpoint's own combined with the change), as
``export --logvar-offsets --material-temperature`` takes them. On procedural data choose
``--prior-weight 0``: the semantic prior reads real photographs. Prints one JSON record with the
choice, the coverage before and after, and the export command.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import torch
from torch import Tensor

from physgm.metrics.physics_metrics import Z90, calibration_logvar_offset, central_coverage
from physgm.model.checkpoint import input_size, load_model
from physgm.model.physgm import PhysGM
from physgm.model.posterior import PhysicsPosterior
from physgm.train.evaluate import view_datamodule

TEMPERATURES = (0.75, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 4.0)
E_OFFSETS = tuple(x / 4 for x in range(-4, 13))  # added log-variance, -1 .. 3 (std x 0.61 .. 4.5)


@dataclasses.dataclass
class ViewSet:
    """The posteriors of one split at one input-view count, with the true values."""

    views: int
    posterior: PhysicsPosterior  # [N]
    log10_E: Tensor  # [N]
    nu: Tensor  # [N]


def collect(model: PhysGM, root: str, split: str, views: int, resolution: int, seed: int = 0) -> ViewSet:
    """The model's posteriors (at its own prior weight) for the split's assets with true physics."""
    dm = view_datamodule(model, root, split, views, resolution, seed=seed, batch_size=8)  # evaluate's views
    posts, log10_E, nu = [], [], []
    for batch in dm.test_dataloader():
        known = batch.true_known
        if not known.any():
            continue
        with torch.no_grad():
            out = model(batch.images, batch.masks, batch.c2w, batch.Ks, batch.features)
        posts.append(out.physics.detach()[known])
        log10_E.append(batch.true_log10_E[known])
        nu.append(batch.true_nu[known])
    if not posts:
        raise SystemExit(
            f"split {split!r} of {root} has no assets with true physics (physical.json 'true'); "
            f"calibrate on generated data (python -m physgm.data.synth --out ROOT)"
        )
    return ViewSet(views, PhysicsPosterior.cat(posts), torch.cat(log10_E), torch.cat(nu))


def pool(sets: list[ViewSet]) -> ViewSet:
    """Several roots' ``ViewSet`` of one input-view count as one."""
    return ViewSet(
        sets[0].views,
        PhysicsPosterior.cat([s.posterior for s in sets]),
        torch.cat([s.log10_E for s in sets]),
        torch.cat([s.nu for s in sets]),
    )


def E_coverage(posterior: PhysicsPosterior, log10_E: Tensor, level: float) -> float:
    """Share of true log10 E inside the posterior's central ``level`` interval."""
    return float(central_coverage(posterior.log10_E_cdf(log10_E), level))


def nu_coverage(posterior: PhysicsPosterior, nu: Tensor) -> float:
    """Share of true nu inside the posterior's 90 % interval."""
    return float(((posterior.nu_mean - nu).abs() <= Z90 * posterior.nu_std).float().mean())


def widened(posterior: PhysicsPosterior, temperature: float, E_offset: float) -> PhysicsPosterior:
    """``posterior`` with its material logits divided by ``temperature`` and ``E_offset`` added to the E
    log-variance (what the head gives with those calibration settings added)."""
    return dataclasses.replace(
        posterior,
        material_logits=posterior.material_logits / temperature,
        z_E_logvar=posterior.z_E_logvar + E_offset,
    )


def choose_E_calibration(
    sets: list[ViewSet],
    level: float = 0.9,
    temperatures: tuple[float, ...] = TEMPERATURES,
    offsets: tuple[float, ...] = E_OFFSETS,
) -> dict:
    """The (temperature, E offset change) of the grid that the module docstring's rule keeps, with its
    scores: ``coverage`` the lowest over ``sets``, ``nll`` the mean over sets of the mean negative log
    density (per decade) of the true log10 E."""
    if sets[0].posterior.E_ranges is None:  # a global-frame E does not read the material
        temperatures = (1.0,)
    rows = []
    for t in temperatures:
        for off in offsets:
            posts = [(widened(s.posterior, t, off), s.log10_E) for s in sets]
            rows.append(
                {
                    "material_temperature": t,
                    "E_offset_change": off,
                    "coverage": min(E_coverage(p, e, level) for p, e in posts),
                    "nll": sum(float(-p.log10_E_log_density(e).mean()) for p, e in posts) / len(posts),
                }
            )
    reaching = [r for r in rows if r["coverage"] >= level]
    if reaching:
        return min(reaching, key=lambda r: r["nll"])
    return max(rows, key=lambda r: (r["coverage"], -r["nll"]))


def calibrate(model: PhysGM, sets: list[ViewSet], level: float = 0.9) -> dict:
    """The calibration of ``model``'s head from its posteriors ``sets`` (taken with the head as it is)."""
    head = model.config.physics_head
    best = choose_E_calibration(sets, level)
    z_nu = [(s.posterior.nu_mean - s.nu).abs() / s.posterior.nu_std for s in sets]
    nu_change = max(float(calibration_logvar_offset(z, level)) for z in z_nu)
    after = {
        f"views{s.views}": {
            "coverage_E": E_coverage(
                widened(s.posterior, best["material_temperature"], best["E_offset_change"]), s.log10_E, level
            ),
            "coverage_nu": nu_coverage(
                dataclasses.replace(s.posterior, z_nu_logvar=s.posterior.z_nu_logvar + nu_change), s.nu
            ),
        }
        for s in sets
    }
    return {
        "material_temperature": head.material_temperature * best["material_temperature"],
        "E_logvar_offset": head.E_logvar_offset + best["E_offset_change"],
        "nu_logvar_offset": head.nu_logvar_offset + nu_change,
        "level": level,
        "E_frame": head.E_frame,
        "before": {
            f"views{s.views}": {
                "assets": len(s.nu),
                "coverage_E": E_coverage(s.posterior, s.log10_E, level),
                "coverage_nu": nu_coverage(s.posterior, s.nu),
            }
            for s in sets
        },
        "after": after,
        "nll_E_after": best["nll"],
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m physgm.train.calibrate", description=__doc__.split("\n")[0])
    p.add_argument("ckpt", type=Path, help="stage-1 or stage-2 checkpoint")
    p.add_argument(
        "--data",
        nargs="+",
        required=True,
        help="PhysAssets roots with splits/ and true physics; their splits pool",
    )
    p.add_argument("--split", default="val")
    p.add_argument("--level", type=float, default=0.9, help="interval level to cover (0 < level < 1)")
    p.add_argument(
        "--prior-weight", type=float, default=None, help="w of the semantic prior (default: the checkpoint's)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the fixed input views (evaluate's)")
    a = p.parse_args(argv)
    if not 0.0 < a.level < 1.0:
        raise SystemExit(f"--level must be between 0 and 1, got {a.level}")
    if not a.ckpt.is_file():
        raise SystemExit(f"checkpoint {a.ckpt} not found")
    model, ckpt = load_model(a.ckpt)
    model.eval()
    if a.prior_weight is not None:
        try:
            model.config = model.config.with_prior_weight(a.prior_weight)
        except ValueError as err:
            raise SystemExit(str(err)) from None
    res = input_size(model, ckpt.hparams)
    sets = [pool([collect(model, root, a.split, v, res, a.seed) for root in a.data]) for v in (1, 4)]
    record = {"ckpt": str(a.ckpt), "data": a.data, "split": a.split, "prior_weight": a.prior_weight}
    record.update(calibrate(model, sets, a.level))
    record["export"] = (
        f"python -m physgm.train.export {a.ckpt} OUT --logvar-offsets {record['E_logvar_offset']:.4g} "
        f"{record['nu_logvar_offset']:.4g} --material-temperature {record['material_temperature']:.4g}"
    )
    print(json.dumps(record))
    return 0


if __name__ == "__main__":
    sys.exit(main())
