"""A photographed object stands on its base: a flat underside for a body that would tip over.

A photo shows an object standing at rest, but one view does not show its underside, and the model
rounds it. The one-view metal can and ceramic mug of ``examples/`` end in a dome 8-15 mm deep on
their 20 cm; set on the ground at rest they roll onto their sides, and dropped 10 cm, they land and
tip over (docs/measurements_sim.md section 44).

``stand_on_base`` releases the placed body at rest on the ground in its photographed pose with the
rigid path. If it turns by more than ``TIP_DEG`` within ``TEST_SECONDS``, the Gaussians below a
horizontal cut are raised onto it and the object is lowered onto the cut. The cut is the shallowest
(in steps of ``CUT_STEP`` of the object's height, at most ``MAX_CUT``) that makes a base: the
opaque Gaussians below it span at least ``BASE_SHARE`` of the object's widest horizontal section,
the body has to tilt by ``MARGIN_DEG`` on it before it tips, and it stands on it. A body that
stands as reconstructed keeps its shape, and so do a round one (a ball, a blob), whose lowest
``MAX_CUT`` spans less than ``BASE_SHARE``, and one no shallow cut gives a base it could stand a
landing on (a body lying on an edge, a duck leaning over its small foot): they roll or fall over as
before.

The test is geometry only: particles fill the Gaussians' volume as the simulation's do, and the
hull of the opaque Gaussians touches the ground, whatever the material.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from scipy.spatial import ConvexHull, QhullError

from physgm.placement import Placement
from physgm.sim.planner.config import PlannerConfig
from physgm.sim.planner.domain import choose_spacing
from physgm.sim.rigid import ContactParams, RigidBody, RigidSimulator
from physgm.sim.sampling import sample_particles

TIP_DEG = 5.0  # a body released at rest that turns more than this does not stand where it was photographed
TEST_SECONDS = 1.0  # how long it is watched at most
MAX_CUT = 0.08  # the deepest cut, a share of the object's height
CUT_STEP = 0.01
# A base spans at least this share of the widest horizontal section (area of the xy convex hull):
# a ball or a blob cut 8 % deep spans 0.18-0.23 of it (docs/measurements_sim.md section 44).
BASE_SHARE = 0.3
# ... and holds the centre of mass so far inside its edge that the body tilts by this much before
# it tips: a landing rocks it. Cut to a base it stood on at rest with 3 degrees to spare, the one-view
# soap dispenser fell over when dropped 10 cm (section 44).
MARGIN_DEG = 10.0
SECTIONS = 20  # horizontal slabs the widest section is looked for in
TEST_DT = 4e-3  # rigid step of the test, s: the body starts at rest and nothing hits hard


@dataclass
class Base:
    """What ``stand_on_base`` did, for report.json."""

    turn_deg: float  # the turn of the body as reconstructed, released at rest (stops past TIP_DEG)
    cut: float  # share of the object's height cut flat (0: the shape is kept)
    cut_m: float  # the same in metres
    moved: int  # Gaussians raised onto the cut
    turn_after_deg: float  # the same with the cut (turn_deg when nothing was cut)

    def as_dict(self) -> dict:
        return {k: round(v, 6) if isinstance(v, float) else v for k, v in self.__dict__.items()}


def _turn(x: np.ndarray, surface: np.ndarray, ground: float, friction: float) -> float:
    """Degrees the body of particles x [P, 3] (equal masses) turns, released at rest on the ground.

    Stops once it has turned past TIP_DEG, else after TEST_SECONDS: a body balanced on a point
    leaves it slowly at first, so a still start does not mean it stands.
    """
    mass = np.full(len(x), 1.0 / len(x))
    body = RigidBody.from_particles(x, mass, contact_points=surface)
    contact = ContactParams(restitution=0.0, friction=friction, ground_height=ground)
    sim = RigidSimulator(body, contact, RigidSimulator.initial_state(body, x, mass, np.zeros_like(x)))
    turn = 0.0
    for _ in range(int(round(TEST_SECONDS / TEST_DT))):
        sim.step(TEST_DT)
        turn = max(turn, float(np.degrees(2.0 * np.arccos(min(1.0, abs(sim.state.q[0]))))))
        if turn > TIP_DEG:
            break
    return turn


def _area(xy: np.ndarray) -> float:
    """Area of the convex hull of points xy [N, 2] (0 for fewer than three, or all on a line)."""
    try:
        return float(ConvexHull(xy).volume) if len(xy) >= 3 else 0.0
    except QhullError:
        return 0.0


def _widest_section(surface: np.ndarray, ground: float, height: float) -> float:
    """Area of the widest horizontal section of points [N, 3] (the largest xy hull of SECTIONS slabs)."""
    edges = ground + height * np.linspace(0.0, 1.0, SECTIONS + 1)
    slab = np.digitize(surface[:, 2], edges[1:-1])
    return max(_area(surface[slab == k, :2]) for k in range(SECTIONS))


def _base(xy: np.ndarray, com: np.ndarray, ground: float, widest: float) -> tuple[float, float]:
    """(share of the widest section, tilt in degrees the body takes before it tips) of the base that
    the points xy [N, 2] of the cut span, for the body's centre of mass com [3] standing on it."""
    try:
        hull = ConvexHull(xy)
    except (QhullError, ValueError):  # fewer than three points, or all on a line: no base
        return 0.0, -90.0
    inside = float(-(hull.equations[:, :2] @ com[:2] + hull.equations[:, 2]).max())  # < 0: outside
    return hull.volume / widest, math.degrees(math.atan2(inside, com[2] - ground))


def _flatten(points: np.ndarray, floor: float, depth: float) -> np.ndarray:
    """Points [N, 3] raised to at least floor + depth, then lowered by depth (the cut on the floor)."""
    out = points.copy()
    out[:, 2] = np.maximum(out[:, 2], floor + depth) - depth
    return out


def stand_on_base(
    placement: Placement,
    min_opacity: float,  # Gaussians at least this opaque carry mass and touch the ground
    ground: float,  # the ground's height, m; the placed object's lowest point is on it
    friction: float,  # the ground's Coulomb friction
    planner: PlannerConfig,  # the particle spacing is the simulation's
) -> tuple[Placement, Base]:
    """``placement`` with its underside cut flat if it would not stand as reconstructed (module docstring)."""
    g = placement.gaussians
    opaque = (g.opacities >= min_opacity).cpu().numpy()
    means = g.means.detach().double().cpu().numpy()
    surface = means[opaque]
    height = float(np.quantile(surface[:, 2], 0.999) - ground)
    extent = float((surface.max(0) - surface.min(0)).max())
    _, spacing = choose_spacing(extent, planner)
    x = sample_particles(g, spacing, min_opacity, planner.fill_interior).x.double().cpu().numpy()
    turn = _turn(x, surface, ground, friction)
    if turn <= TIP_DEG or not height > 0:
        return placement, Base(turn, 0.0, 0.0, 0, turn)

    widest = _widest_section(surface, ground, height)
    if not widest > 0:
        return placement, Base(turn, 0.0, 0.0, 0, turn)
    for k in range(1, int(round(MAX_CUT / CUT_STEP)) + 1):
        depth = k * CUT_STEP * height
        body = _flatten(x, ground, depth)
        xy = surface[surface[:, 2] <= ground + depth, :2]
        share, margin = _base(xy, body.mean(0), ground, widest)
        if share < BASE_SHARE or margin < MARGIN_DEG:
            continue
        after = _turn(body, _flatten(surface, ground, depth), ground, friction)
        if after <= TIP_DEG:
            moved = int((means[:, 2] < ground + depth).sum())
            flat = torch.from_numpy(_flatten(means, ground, depth)).to(g.means)
            shift = placement.object_to_world.copy()
            shift[2, 3] -= depth  # the affine part; the raised underside is recorded in Base
            placed = replace(placement, gaussians=replace(g, means=flat), object_to_world=shift)
            return placed, Base(turn, k * CUT_STEP, depth, moved, after)
    return placement, Base(turn, 0.0, 0.0, 0, turn)


def describe(base: dict | None) -> str | None:
    """A line for the user when the underside was cut (``base``: ``Base.as_dict()``), else None."""
    if base is None or base["cut"] == 0.0:
        return None
    return (
        f"set down as reconstructed, the object turned over by more than {TIP_DEG:g} degrees, so its "
        f"lowest {base['cut_m'] * 1000:.1f} mm ({100 * base['cut']:.0f} % of its height) were cut flat for "
        "it to stand as photographed (object.stand=false keeps its shape)"
    )
