"""The planner's error models: how far, in pixels, each cheaper simulation strays from full MPM.

Deformation model (object size L, density rho, impact speed v, P-wave speed c_p):
    sag under gravity          d_sag  = rho g L^2 / E
    elastic impact compression d_imp  = v L / c_0        (c_0 = sqrt(E / rho): 1/2 m v^2 = 1/2 (E L) d^2)
    plastic dent past yield    d_pl   = rho L v^2 / (2 sigma_y)   if rho c_p v > sigma_y
All three are order-of-magnitude estimates: the plan reports them so the choice can be audited.
The rigid path errs by the whole deformation; a stiffness cap by the extra deformation of the
softer E' (``stiffness_cap``), and after a landing that dents by its dent term
(``STIFFNESS_DENT_GAIN``); the bulk cap by its own model (``physgm.sim.bulk_cap``).
``pixels_per_metre`` turns metres into pixels at the closest output camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from physgm.cameras import Cameras


@dataclass
class Deformation:
    """Estimated visible deformation of the object in the scene, metres."""

    sag: float
    impact: float
    plastic: float
    flows: bool  # granular / fluid / prescribed motion: unbounded

    @property
    def total(self) -> float:
        return math.inf if self.flows else self.sag + self.impact + self.plastic


def pixels_per_metre(
    cameras: Cameras,
    points: Tensor,  # [P, 3] world points of the object, m
) -> float:
    """Largest image-plane scale f / depth over cameras and points (the closest view), px/m."""
    pts = points.detach().to(cameras.c2w)
    cam = pts @ cameras.viewmats[:, :3, :3].transpose(-1, -2) + cameras.viewmats[:, None, :3, 3]  # [C, P, 3]
    depth = cam[..., 2]
    if not (depth > 0).any():
        raise ValueError(
            "the object is behind every output camera; check the cameras' c2w (OpenCV: +z looks forward)"
        )
    focal = torch.maximum(cameras.Ks[:, 0, 0], cameras.Ks[:, 1, 1])  # [C]
    # A point at depth ~0 would give an infinite scale; the object cannot come closer than 1 mm.
    scale = focal[:, None] / depth.clamp_min(1e-3)
    return float(scale[depth > 0].max())


def deformation_estimate(
    E: float,  # Pa
    density: float,  # kg/m^3
    size: float,  # largest object extent, m
    impact_speed: float,  # m/s
    gravity: float = 9.81,  # m/s^2
    yield_stress: float | None = None,  # Pa; None: purely elastic
    flows: bool = False,
    wave_factor: float = 1.0,  # P-wave modulus / E, e.g. (1 - nu) / ((1 + nu)(1 - 2 nu))
) -> Deformation:
    """Order-of-magnitude deformation of the object in metres (see module docstring).

    Both choices are the conservative ones: the compression uses the bar speed sqrt(E / rho) (a
    free block, larger than the constrained P-wave estimate), the impact stress the P-wave speed
    sqrt(wave_factor E / rho) (larger stress, earlier yield).
    """
    if E <= 0 or density <= 0 or size <= 0:
        raise ValueError(
            f"deformation_estimate needs positive E, density and size, got {E}, {density}, {size}"
        )
    sag = density * gravity * size**2 / E
    impact = impact_speed * size / math.sqrt(E / density)
    c_p = math.sqrt(wave_factor * E / density)
    plastic = 0.0
    if yield_stress is not None and yield_stress > 0:
        if density * gravity * size > yield_stress:
            flows = True  # slumps under its own weight
        elif density * c_p * impact_speed > yield_stress:  # impact stress rho c_p v
            plastic = density * size * impact_speed**2 / (2 * yield_stress)
    return Deformation(sag, impact, plastic, flows)


# A landing that dents moves with the wave speed under a stiffness cap too, more than under the bulk
# cap (bulk_cap.DENT_GAIN: there the shear modulus is kept). Mean shift per unit relative change of
# c_p (sqrt(E' / E)) per object size in pixels, measured on six plasticine drops with E lowered
# (E 1e6-1e8 Pa, by 20-50 %; docs/measurements_sim.md section 20): 0.0065-0.073, the largest for
# the softest lump, whose flow after landing follows E. The largest, rounded up, is taken.
STIFFNESS_DENT_GAIN = 0.075


def stiffness_dent_floor(E: float, budget_px: float, size_px: float) -> float:
    """Smallest E' whose dent term, ``STIFFNESS_DENT_GAIN`` (1 - sqrt(E' / E)) x ``size_px``
    (``bulk_cap.wave_shift_px``: c_p grows as sqrt(E) at a fixed nu), stays within ``budget_px``, Pa."""
    keep = 1.0 - budget_px / (STIFFNESS_DENT_GAIN * size_px)
    return E * keep * keep if keep > 0.0 else 0.0


def stiffness_cap(
    E: float,  # Pa, true stiffness
    density: float,  # kg/m^3
    size: float,  # m
    impact_speed: float,  # m/s
    bound: float,  # extra deformation allowed, m
    gravity: float = 9.81,
) -> float:
    """Smallest E' <= E whose elastic deformation exceeds that at E by at most ``bound``, Pa.

    Elastic deformation is a / E + b / sqrt(E) (sag + impact); with u = 1 / sqrt(E') the
    condition a u^2 + b u = d(E) + bound is a quadratic with one positive root.
    Monotone: a larger bound gives a smaller (cheaper) cap.
    """
    if bound < 0:
        raise ValueError(f"bound must be >= 0, got {bound}")
    a = density * gravity * size**2
    b = impact_speed * size * math.sqrt(density)
    target = a / E + b / math.sqrt(E) + bound
    if a > 0:
        u = (-b + math.sqrt(b * b + 4 * a * target)) / (2 * a)
    elif b > 0:
        u = target / b
    else:
        return E
    return min(E, 1.0 / (u * u))


def impact_speed(z_bottom: float, ground: float | None, vz0: float, gravity: float) -> float:
    """Speed at which the lowest point reaches the ground (0 without a ground), m/s."""
    if ground is None:
        return abs(vz0)
    fall = max(z_bottom - ground, 0.0)
    return math.sqrt(vz0 * vz0 + 2 * gravity * fall) if vz0 <= 0 or fall > 0 else abs(vz0)
