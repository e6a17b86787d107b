"""Choosing the physics to simulate: the posterior mean, K posterior samples, explicit overrides.

Rules (each choice records *why* in physics.json):
* an explicit override (``physics.material``, ``physics.E``, ``physics.nu``, ``physics.density``)
  always wins;
* otherwise the run "mean" takes the most likely material and the posterior mean of log10 E and
  nu, and run "sample<k>" a draw from the posterior;
* a predicted E or nu is kept if it lies in the chosen material's typical range, else projected
  onto that range, whether the material was predicted or overridden: the model's E and nu heads
  are not conditioned on its material, and a "plastic" with the stiffness of rubber would be
  neither (the simulator would run a rubbery plastic through tens of thousands of sub-steps
  where a rigid body would do); physics.json says when a value was projected;
* a .ply input has no prediction: the material must be given, E and nu default to its table values.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING

from physgm.errors import UserError
from physgm.physics.materials import MATERIAL_NAMES, PhysicsSpec, get_material
from physgm.pipeline.config import PhysicsOverrides

if TYPE_CHECKING:  # importing physgm.model pulls in torch; a .ply run never needs the model
    from physgm.model.posterior import PhysicsPosterior, PhysicsSample

NU_MAX = 0.49  # = physgm.model.posterior.NU_MAX: the simulator's Lame lambda blows up at nu = 0.5


@dataclass
class PhysicsChoice:
    """One future to simulate."""

    name: str  # "mean" or "sample<k>"
    material: str
    E: float  # Pa
    nu: float
    density: float | None  # kg/m^3; None: the material table's
    why: dict[str, str] = field(default_factory=dict)  # field -> reason

    def spec(self) -> PhysicsSpec:
        """The physics ``physgm.sim.gaussian_trajectory.simulate`` runs."""
        return PhysicsSpec(self.material, self.E, self.nu, self.density)

    def label(self) -> str:
        return f"{self.name}: {self.material}, E={self.E:.3g} Pa, nu={self.nu:.2f}"


def posterior_summary(post: PhysicsPosterior) -> dict:
    """JSON view of a [1] posterior: material probabilities, E and nu with their spread."""
    probs = post.material_probs[0].tolist()
    m, s = float(post.log10_E_mean[0]), float(post.log10_E_std[0])
    order = sorted(range(len(probs)), key=lambda i: -probs[i])
    return {
        "material_probs": {MATERIAL_NAMES[i]: round(probs[i], 5) for i in range(len(probs))},
        "material_top3": [[MATERIAL_NAMES[i], round(probs[i], 4)] for i in order[:3]],
        "log10_E": {"mean": round(m, 4), "std": round(s, 4)},
        "E_Pa": {"mean": 10.0**m, "low_1sigma": 10.0 ** (m - s), "high_1sigma": 10.0 ** (m + s)},
        "nu": {"mean": round(float(post.nu_mean[0]), 4), "std": round(float(post.nu_std[0]), 4)},
    }


def _in_range(value: float, lo: float, hi: float) -> float:
    return min(max(value, lo), hi)


def _choice(name: str, sample: PhysicsSample | None, over: PhysicsOverrides, what: str) -> PhysicsChoice:
    why: dict[str, str] = {}
    if over.material is not None:
        material, why["material"] = over.material, "override (physics.material)"
    elif sample is not None:
        material, why["material"] = MATERIAL_NAMES[int(sample.material[0, 0])], what
    else:
        raise UserError(
            "a .ply input has no predicted physics; give the material, e.g. physics.material=rubber (one "
            f"of: {', '.join(MATERIAL_NAMES)})"
        )
    table = get_material(material)
    values = {}
    for key, predicted, (lo, hi), default in (
        ("E", None if sample is None else float(sample.youngs_modulus()[0, 0]), table.E_range, table.E),
        ("nu", None if sample is None else float(sample.poisson_ratio()[0, 0]), table.nu_range, table.nu),
    ):
        given = getattr(over, key)
        if given is not None:
            values[key], why[key] = float(given), f"override (physics.{key})"
        elif predicted is None:
            values[key], why[key] = float(default), f"material table default for {material}"
        elif not lo <= predicted <= hi:
            values[key] = _in_range(predicted, lo, hi)
            why[key] = f"{what}, {predicted:.3g} projected onto the {material} range [{lo:.3g}, {hi:.3g}]"
        else:
            values[key], why[key] = predicted, what
    values["nu"] = min(values["nu"], NU_MAX)
    why["density"] = (
        "override (physics.density)"
        if over.density is not None
        else f"material table ({table.density:g} kg/m^3)"
    )
    return PhysicsChoice(name, material, values["E"], values["nu"], over.density, why)


def choose_physics(post: PhysicsPosterior | None, over: PhysicsOverrides, seed: int) -> list[PhysicsChoice]:
    """The runs to simulate: "mean" first, then ``over.samples`` posterior draws."""
    if post is None and over.samples:
        raise UserError(
            "physics.samples needs the model's physics posterior; a .ply input has none (drop "
            "physics.samples)"
        )
    mean = _choice("mean", None if post is None else post.mean(), over, "posterior mean")
    runs = [mean]
    if post is not None and over.samples:
        import torch

        gen = torch.Generator(device=post.material_logits.device).manual_seed(seed)
        draws = post.sample(over.samples, generator=gen)
        for k in range(over.samples):
            runs.append(
                _choice(f"sample{k}", draws[:, k : k + 1], over, f"posterior sample {k} (seed {seed})")
            )
    for r in runs:
        if not (math.isfinite(r.E) and r.E > 0 and math.isfinite(r.nu)):
            raise ValueError(f"physics choice {r.label()} is not finite; the model output is broken")
    return runs


def physics_json(
    post: PhysicsPosterior | None,
    over: PhysicsOverrides,
    runs: list[PhysicsChoice],
    videos: dict[str, str],
    domain_real: float | None = None,
) -> dict:
    """Contents of physics.json. ``domain_real``: the model's domain gate, P(the views show a real
    object), which weighs the semantic prior's expert against the procedural one (None: no gate)."""
    posterior = None if post is None else posterior_summary(post)
    if posterior is not None and domain_real is not None:
        posterior["domain_real"] = round(domain_real, 4)
    return {
        "source": "model" if post is not None else "none (a .ply input has no prediction)",
        "posterior": posterior,
        "overrides": {k: v for k, v in asdict(over).items() if k != "samples"},
        "samples": over.samples,
        "runs": [{**asdict(r), "video": videos.get(r.name)} for r in runs],
        "rules": "explicit overrides win; otherwise the posterior mean (run 'mean') or a posterior draw "
        "(runs 'sample<k>'); predicted E and nu outside the chosen material's typical range are projected "
        "onto it",
    }
