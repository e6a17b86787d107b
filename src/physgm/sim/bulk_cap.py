"""Bulk-stiffness cap: fewer explicit sub-steps for nearly incompressible solids, shear kept.

The explicit step follows the fastest wave, c_p = sqrt((lam + 2 mu) / rho). At nu -> 0.5 the
bulk modulus K = lam + 2 mu / 3 dwarfs the shear modulus mu and c_p / c_s = sqrt(2 (1 - nu) /
(1 - 2 nu)) grows without bound (rubber, nu = 0.48: 5.1), so the step is set by a volume change
of a fraction of a percent. The cap keeps mu (the shape response: bending, shear, the wobble of
a jelly) and lowers nu until c_p / c_s equals a ratio r, nu_r = (r^2 - 2) / (2 (r^2 - 1)); the
step then grows by the ratio of the P-wave speeds (rubber at r = 2.6: 1.96x).

What the eye can see of it, measured (docs/measurements_sim.md, "Fewer sub-steps"): the
constrained (P-wave) modulus M = lam + 2 mu falls with nu (rubber: 26 mu -> 4 mu at r = 2), and
a body whose base is held by friction, or hit flat, responds with M more than with E:
- a block resting on the ground sags more and oscillates with a larger amplitude after gravity
  is switched on (8 cm rubber, E = 2e4 Pa: CoM moved up to 1.4 mm at r = 2, 0.33 mm at r = 3);
  the deformation term is the planner's sag + impact estimate with M in place of E (M bounds
  the held base from above: 2.2 / 0.74 mm predicted);
- an elastic impact rebounds differently, in proportion to the change of c_p (the contact of a
  flat face lasts ~2 L / c_p): a 15 cm rubber cube dropped 0.5 m moved 8.6 px on average at
  r = 2 and 4.2 px at r = 3. ``rebound_px`` scales that with the relative change of c_p and
  the object's size in pixels; the same factor fits the stiffness cap's rebound (plastic,
  E -2 % / -20 %: 0.12 / 1.3 px). With the default 0.5 px bound an impact therefore never
  pays for a cap of a 15 cm object at 256 px: the bulk cap is for resting bodies (not for
  gripped ones: a stretched body necks by nu, and the planner caps nothing that boxes drive);
- a lump that lands and dents (plasticine) does not rebound, and the elastic compression at M
  over-predicts what the eye sees 3-10x: the clip moves by ``dent_px``, the rebound's form with a
  gain 16x smaller, fitted to eight plasticine drops (docs/measurements_sim.md section 20).
The cap takes the smallest r >= ``min_ratio`` whose predicted error stays within the budget.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from physgm.sim.constitutive import MaterialParams

# Rebound sensitivity of an elastic impact: a bounce moves by about this many object sizes per
# unit relative change of the P-wave speed (mean over frames and Gaussians). Fitted to drops of a
# 15 cm cube at 256 px (51.6 px across; docs/measurements_sim.md, "Fewer sub-steps"): plastic,
# E -2 % / -20 %: 0.12 / 1.3 px (0.23-0.24); rubber's bulk cap at r = 3 / 2: 4.2 / 8.6 px (0.20 /
# 0.27); measured again on jelly (E 1e5 Pa, section 20): r = 3 / 2.5: 4.38 / 6.54 px (0.89 /
# 0.52), a wobbling body whose bounce a small change sends elsewhere. The largest is taken.
REBOUND_GAIN = 0.9

# A dent: the mean shift of a lump that lands and yields, per unit relative change of the P-wave
# speed and per object size in pixels. Fitted to plasticine drops at 12 cells across (E 1e5-1e7 Pa,
# nu 0.4-0.45, c_p / c_s capped to 2-2.8; docs/measurements_sim.md section 20): 0.0043-0.0161 over
# 15 runs, so the largest, rounded up, is taken.
DENT_GAIN = 0.017

# Constitutive models whose pressure enters the yield or flow law: a capped bulk modulus would
# change how they flow, not only how much they compress.
PRESSURE_SENSITIVE = frozenset({"drucker_prager", "fluid"})


def wave_ratio(nu: float) -> float:
    """c_p / c_s = sqrt(2 (1 - nu) / (1 - 2 nu)) of an isotropic solid with Poisson ratio nu."""
    if not -1.0 < nu < 0.5:
        raise ValueError(f"Poisson ratio nu={nu!r} must lie in (-1, 0.5)")
    return math.sqrt(2.0 * (1.0 - nu) / (1.0 - 2.0 * nu))


def nu_for_wave_ratio(ratio: float) -> float:
    """The Poisson ratio whose c_p / c_s is ``ratio`` (> 1; ratio 2 gives nu = 1/3)."""
    if not ratio > 1.0:
        raise ValueError(f"wave-speed ratio c_p / c_s = {ratio!r} must be > 1")
    return (ratio * ratio - 2.0) / (2.0 * (ratio * ratio - 1.0))


def p_modulus(material: MaterialParams) -> float:
    """Constrained (P-wave) modulus lam + 2 mu, Pa."""
    return material.lam + 2.0 * material.mu


def capped_material(material: MaterialParams, ratio: float) -> MaterialParams:
    """``material`` with the same shear modulus and c_p / c_s at most ``ratio``."""
    if wave_ratio(material.nu) <= ratio:
        return material
    nu = nu_for_wave_ratio(ratio)
    return material.with_elasticity(E=2.0 * material.mu * (1.0 + nu), nu=nu)


def wave_shift_px(gain: float, material: MaterialParams, capped: MaterialParams, size_px: float) -> float:
    """``gain`` x the relative fall of the P-wave speed x the object's size, pixels: the form of
    every impact term of the caps (a rebound, a dent; the stiffness cap's dent in the planner)."""
    return gain * max(1.0 - capped.wave_speed() / material.wave_speed(), 0.0) * size_px


def rebound_px(material: MaterialParams, capped: MaterialParams, size_px: float) -> float:
    """Predicted shift of an elastic rebound when ``material`` is simulated as ``capped``, pixels."""
    return wave_shift_px(REBOUND_GAIN, material, capped, size_px)


def dent_px(material: MaterialParams, capped: MaterialParams, size_px: float) -> float:
    """Predicted shift of a lump that lands and dents when ``material`` is simulated as ``capped``, pixels."""
    return wave_shift_px(DENT_GAIN, material, capped, size_px)


@dataclass(frozen=True)
class BulkCap:
    """A chosen bulk cap: the material to simulate and its predicted visual error."""

    material: MaterialParams  # capped E and nu, same mu
    ratio: float  # c_p / c_s after the cap
    deformation_px: float  # extra sag (+ impact compression, unless it dents) at the P-wave modulus, pixels
    rebound_px: float  # change of an elastic rebound, pixels (0 without an elastic impact)
    dent_px: float = 0.0  # change of a landing that dents, pixels (0 without one)

    @property
    def predicted_px(self) -> float:
        # The dent term was fitted to whole clips, their sag included, so it is not added to the
        # sag term: the larger of the two counts (the sag term bounds lumps softer than those fitted).
        return max(self.deformation_px, self.dent_px) + self.rebound_px


def choose_bulk_cap(
    material: MaterialParams,
    deformation_px: Callable[[float], float],  # modulus (Pa) -> sag + impact deformation, pixels
    size_px: float,  # object's largest extent in pixels
    elastic_impact: bool,
    budget_px: float,
    min_ratio: float,
    force: bool = False,
    dent: bool = False,  # it lands and yields (then ``deformation_px`` should leave the impact out)
) -> BulkCap | None:
    """The strongest bulk cap (smallest ratio >= min_ratio) whose predicted error <= budget_px.

    None when the model's pressure matters to its plasticity, when nu is already below the
    ratio's, or when even the mildest cap costs more than the budget. ``force`` takes min_ratio
    whatever its error (benchmarks measure it instead).
    """
    if elastic_impact and dent:
        raise ValueError("an impact is either elastic (it rebounds) or a dent, not both")
    if material.model in PRESSURE_SENSITIVE or wave_ratio(material.nu) <= min_ratio:
        return None
    base = deformation_px(p_modulus(material))

    def option(ratio: float) -> BulkCap:
        capped = capped_material(material, ratio)
        rebound = rebound_px(material, capped, size_px) if elastic_impact else 0.0
        dented = dent_px(material, capped, size_px) if dent else 0.0
        return BulkCap(capped, ratio, max(deformation_px(p_modulus(capped)) - base, 0.0), rebound, dented)

    strongest = option(min_ratio)
    if force or strongest.predicted_px <= budget_px:
        return strongest
    # The error falls monotonically as the ratio rises towards the material's own: bisect.
    lo, hi = min_ratio, wave_ratio(material.nu)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if option(mid).predicted_px <= budget_px else (mid, hi)
    best = option(hi)
    return best if best.ratio < wave_ratio(material.nu) * (1 - 1e-6) else None
