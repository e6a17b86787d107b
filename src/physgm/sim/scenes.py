"""Scenes: gravity + boundary conditions + initial velocities, one registry of drivers.

A scene config (conf/sim/scene/<name>.yaml) plus the object's rest particles go through the
driver registered under that name, which places the object, sets initial velocities and builds
the boundary conditions:

    setup = build_scene("drop", x, height=0.2)        # overrides win over the YAML
    solver = MPMSolver(Particles(setup.x, volume, material, v=setup.v), materials,
                       GridSpec.fit(setup.reach_lo, setup.reach_hi, dx), setup.scene)

``reach_lo`` / ``reach_hi`` bound where the particles can go during ``duration`` (for fitting
the grid; the planner may refine them).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import yaml

from physgm.resources import package_file
from physgm.sim.mpm.boundary import GroundPlane, VelocityBox
from physgm.sim.mpm.scene import Scene
from physgm.sim.mpm.walls import PeriodicAxis, SideWall

SCENE_DIR = package_file("conf", "sim", "scene")  # ships inside the package (physgm.resources)


@dataclass
class SceneSetup:
    """A scene applied to one object: placed particles, their velocities and the boundaries."""

    scene: Scene
    x: np.ndarray  # [P, 3] placed rest positions, m
    v: np.ndarray  # [P, 3] initial velocities, m/s
    duration: float  # s, suggested simulated time
    reach_lo: np.ndarray  # [3] m, lower corner of the region the particles can reach
    reach_hi: np.ndarray  # [3] m
    driver_work: bool = False  # the scene moves particles by prescribed velocities (adds energy)
    stretch: tuple[int, float] | None = None  # (axis, largest local stretch) a scene pulls the body to


def _ground(cfg: dict) -> GroundPlane | None:
    g = cfg.get("ground")
    return None if g is None else GroundPlane(**g)


def _boundaries(cfg: dict) -> dict:
    """Side walls and periodic axes of a scene config (``walls: [{axis, position, solid, mode}]``,
    ``periodic: [{axis, lo, hi}]``), as Scene keyword arguments."""
    try:
        walls = tuple(SideWall(**w) for w in cfg.get("walls") or ())
        periodic = tuple(PeriodicAxis(**p) for p in cfg.get("periodic") or ())
    except TypeError as e:
        raise ValueError(
            f"scene walls / periodic entries must be mappings with keys (axis, position, solid, mode) / "
            f"(axis, lo, hi): {e}"
        ) from None
    return {"walls": walls, "periodic": periodic}


def _vec(value, name: str) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise ValueError(f"scene setting {name}={value!r} must be three finite numbers")
    return v


def _fall_reach(x: np.ndarray, v: np.ndarray, gravity: np.ndarray, duration: float, floor: float | None):
    """Box swept by a ballistic object (bounded below by the floor), plus one object size of spread."""
    lo, hi = x.min(0), x.max(0)
    size = float((hi - lo).max())
    v_mean = v.mean(0)
    travel = np.abs(v_mean) * duration + 0.5 * np.abs(gravity) * duration**2
    reach_lo, reach_hi = lo - travel - 0.5 * size, hi + travel + 0.5 * size
    if floor is not None:
        reach_lo[2] = max(floor - 0.1 * size, min(reach_lo[2], lo[2]))
        reach_hi[2] = hi[2] + max(0.0, float(v_mean[2])) ** 2 / (2 * max(abs(gravity[2]), 1e-9)) + 0.5 * size
    return reach_lo, reach_hi


def _lowest_surface_at(x: np.ndarray, z: float, surface: float) -> np.ndarray:
    """Particles x [P, 3] moved along z so their material's lowest surface (``surface`` under the
    lowest centre, ``build_scene``) is at height z, m."""
    return x - np.array([0.0, 0.0, x[:, 2].min() - surface - z])


def drop(x: np.ndarray, material: np.ndarray, cfg: dict, surface: float) -> SceneSetup:
    """Place the object's lowest point ``height`` above the ground with velocity ``velocity``;
    gravity pulls it down."""
    ground = _ground(cfg)
    floor = ground.height if ground is not None else 0.0
    x = _lowest_surface_at(x, floor + float(cfg["height"]), surface)
    v = np.tile(_vec(cfg.get("velocity", (0, 0, 0)), "velocity"), (len(x), 1))
    gravity = _vec(cfg["gravity"], "gravity")
    duration = float(cfg["duration"])
    lo, hi = _fall_reach(x, v, gravity, duration, floor if ground is not None else None)
    scene = Scene(gravity=tuple(gravity), ground=ground, **_boundaries(cfg))
    return SceneSetup(scene, x, v, duration, lo, hi)


def _peak_stretch(
    s: np.ndarray,  # [P] particle coordinates along the pulling axis, m
    faces: np.ndarray,  # [2] the grips' inner faces, m
    extension: float,  # m the grips add to the length
) -> float:
    """Largest local stretch of the part between the grips, read as a bar of varying section.

    One force runs through the bar, so its strain goes as 1 / A(s): eps(s) = extension / (A(s)
    int ds / A). A(s) is the particles' density along the axis, smoothed over a twelfth of the
    span (a grid cell at the planner's default) so a lattice's layers do not alias. A prism gets
    its mean stretch; a round blob held by its ends about 1.3x that next to the grips.
    """
    width = (float(s.max() - s.min()) or 1.0) / 12.0
    at = np.linspace(faces[0], faces[1], 65)  # [65]
    density = np.zeros_like(at)
    for chunk in np.array_split(s, max(1, len(s) // 65_536)):  # [65, n] at a time: bounded memory
        density += np.exp(-0.5 * ((at[:, None] - chunk[None, :]) / width) ** 2).sum(1)
    strain = extension / (density * np.trapezoid(1.0 / density, at))
    return 1.0 + float(strain.max())


def stretch(x: np.ndarray, material: np.ndarray, cfg: dict, surface: float) -> SceneSetup:
    """Two grips, each holding ``grip_fraction`` of the particles at one end, move apart at
    ``speed`` until the body's length is ``ratio`` x its rest length.

    A ``slip`` grip prescribes only the velocity along the axis, so the held ends narrow with the
    body and a prism is left in uniform uniaxial tension; a ``clamp`` holds the ends at their
    width. The setup names the stretch, for which the particles are split along the axis
    (``planner.stretch_splits``). The grips hold grid nodes, not particles, so they need to be
    about a cell deep: at the planner's 12 cells across, 10 % of a prism is 1.2 cells.
    """
    a = int(cfg["axis"])
    speed, ratio, frac = float(cfg["speed"]), float(cfg["ratio"]), float(cfg["grip_fraction"])
    if not (speed > 0 and ratio > 1 and 0 < frac < 0.5):
        raise ValueError(
            f"stretch needs speed > 0, ratio > 1, 0 < grip_fraction < 0.5; got {speed}, {ratio}, {frac}"
        )
    kind = str(cfg["grip"])
    if kind not in ("slip", "clamp"):
        raise ValueError(f"stretch grip must be slip or clamp, got {kind!r}")
    axes = tuple(kind == "clamp" or i == a for i in range(3))
    lo, hi = x.min(0), x.max(0)
    length = float(hi[a] - lo[a])
    pad = 0.5 * float((hi - lo).max())
    stop = (ratio - 1.0) * length / (2.0 * speed)
    # Each grip holds that share of the particles, not of the length: the rounded end of a blob
    # is thin, and a grip on its tip alone pulls the tip off.
    inner = np.quantile(x[:, a], [frac, 1.0 - frac])
    boxes = []
    for sign, end, face in ((-1.0, lo[a], inner[0]), (1.0, hi[a], inner[1])):
        b_lo, b_hi = lo - pad, hi + pad
        if sign < 0:
            b_lo[a], b_hi[a] = end - pad, face
        else:
            b_lo[a], b_hi[a] = face, end + pad
        vel = np.zeros(3)
        vel[a] = sign * speed
        # The grips hold nodes only: their particles follow the nodes, so the strain runs
        # smoothly into the grip (VelocityBox: carried particles tear off at the grip's edge).
        grip = VelocityBox(tuple(b_lo), tuple(b_hi), tuple(vel), 0.0, stop, hold=True, axes=axes, carry=False)
        boxes.append(grip)
    gravity = _vec(cfg.get("gravity", (0, 0, 0)), "gravity")
    duration = float(cfg["duration"])
    grow = np.zeros(3)
    grow[a] = 0.5 * (ratio - 1.0) * length
    reach_lo = lo - grow - 0.25 * pad - 0.5 * np.abs(gravity) * duration**2
    reach_hi = hi + grow + 0.25 * pad
    scene = Scene(gravity=tuple(gravity), ground=_ground(cfg), boxes=tuple(boxes), **_boundaries(cfg))
    peak = _peak_stretch(x[:, a], inner, (ratio - 1.0) * length)
    return SceneSetup(
        scene, x.copy(), np.zeros_like(x), duration, reach_lo, reach_hi, driver_work=True, stretch=(a, peak)
    )


def push(x: np.ndarray, material: np.ndarray, cfg: dict, surface: float) -> SceneSetup:
    """Throw the object at ``speed`` along ``axis`` into a fixed wall ``wall_gap`` ahead of it."""
    a = int(cfg["axis"])
    ground = _ground(cfg)
    floor = ground.height if ground is not None else 0.0
    x = _lowest_surface_at(x, floor + float(cfg.get("lift", 0.0)), surface)
    lo, hi = x.min(0), x.max(0)
    size = float((hi - lo).max())
    w_lo, w_hi = lo - size, hi + size
    w_lo[a] = hi[a] + float(cfg["wall_gap"])
    w_hi[a] = w_lo[a] + float(cfg["wall_thickness"])
    wall = VelocityBox(tuple(w_lo), tuple(w_hi), (0.0, 0.0, 0.0))
    v = np.zeros_like(x)
    v[:, a] = float(cfg["speed"])
    gravity = _vec(cfg["gravity"], "gravity")
    duration = float(cfg["duration"])
    reach_lo, reach_hi = _fall_reach(x, v, gravity, duration, floor if ground is not None else None)
    reach_hi[a] = min(reach_hi[a], w_hi[a])
    reach_lo[a] = min(reach_lo[a], lo[a] - abs(float(cfg["speed"])) * duration)
    scene = Scene(gravity=tuple(gravity), ground=ground, boxes=(wall,), **_boundaries(cfg))
    return SceneSetup(scene, x, v, duration, reach_lo, reach_hi)


def two_objects(x: np.ndarray, material: np.ndarray, cfg: dict, surface: float) -> SceneSetup:
    """Object with material index 1 starts ``gap`` above object 0, which rests on the ground."""
    top, bottom = material == 1, material == 0
    if not top.any() or not bottom.any() or not (top | bottom).all():
        raise ValueError("two_objects needs particles with material index 0 (bottom) and 1 (top) only")
    ground = _ground(cfg)
    floor = ground.height if ground is not None else 0.0
    x = x.copy()
    x[bottom] = _lowest_surface_at(x[bottom], floor, surface)
    # The gap is between the bodies' surfaces: the top of the lower one is surface above its centres.
    x[top] = _lowest_surface_at(x[top], x[bottom, 2].max() + surface + float(cfg["gap"]), surface)
    # Centre the top object over the bottom one.
    x[top, :2] += x[bottom, :2].mean(0) - x[top, :2].mean(0)
    v = np.zeros_like(x)
    v[top] = _vec(cfg.get("velocity", (0, 0, 0)), "velocity")
    gravity = _vec(cfg["gravity"], "gravity")
    duration = float(cfg["duration"])
    lo, hi = _fall_reach(x, v, gravity, duration, floor if ground is not None else None)
    scene = Scene(gravity=tuple(gravity), ground=ground, **_boundaries(cfg))
    return SceneSetup(scene, x, v, duration, lo, hi)


# (rest particles [P, 3] m, material index [P], settings, surface m; ``build_scene``) -> setup
SceneDriver = Callable[[np.ndarray, np.ndarray, dict, float], SceneSetup]
SCENES: dict[str, SceneDriver] = {"drop": drop, "stretch": stretch, "push": push, "two_objects": two_objects}


def load_scene_config(name: str) -> dict:
    """The YAML settings of scene ``name`` (conf/sim/scene/<name>.yaml)."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; known scenes: {', '.join(SCENES)}")
    return yaml.safe_load((SCENE_DIR / f"{name}.yaml").read_text())


def build_scene(
    name: str, x: np.ndarray, material: np.ndarray | None = None, surface: float = 0.0, **overrides
) -> SceneSetup:
    """Apply scene ``name`` to rest particles ``x`` [P, 3] (m); ``overrides`` replace YAML settings.

    ``surface``: how far the material reaches below a particle's centre, m (half the spacing of a
    particle lattice; 0 takes the particles as points). Heights and gaps are the material's: a
    drop's ``height`` is from the ground to the object's lowest surface, so an object set on the
    ground (``height`` 0, a push's ``lift`` 0) rests there, as the rigid path and the particle
    contact both take it (``particle_ground``).
    """
    if not (math.isfinite(surface) and surface >= 0.0):
        raise ValueError(f"surface must be a finite distance >= 0 m, got {surface!r}")
    cfg = load_scene_config(name)
    unknown = set(overrides) - set(cfg)
    if unknown:
        raise ValueError(f"scene {name!r} has no settings {sorted(unknown)}; it has {sorted(cfg)}")
    cfg.update(overrides)
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or len(x) == 0 or not np.isfinite(x).all():
        raise ValueError(f"scene {name!r} needs finite particle positions of shape [P, 3], got {x.shape}")
    material = np.zeros(len(x), np.int32) if material is None else np.asarray(material)
    if not math.isfinite(float(cfg.get("duration", 1.0))):
        raise ValueError("scene duration must be finite")
    return SCENES[name](x, material, cfg, float(surface))
