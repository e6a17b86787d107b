"""PhysGaussian's simulation config JSON (XPandora/PhysGaussian, config/*.json) for ``simulate.py``.

    python simulate.py input=model.ply physgaussian_config=ficus_config.json

PhysGaussian drops Gaussians fainter than ``opacity_threshold``, rotates the rest
(``rotation_degree`` about ``rotation_axis``), scales them so their largest extent is ``scale``
(default 1) and centres their bounding box at (1, 1, 1) of its MPM space, with
``mpm_space_vertical_upward_axis`` pointing up; E, nu, density and g are SI, so that space is in
metres. Its keys map onto simulate.yaml as follows (docs/interop.md has the full table):

* ``material``, ``E``, ``nu``, ``density`` -> ``physics.*`` (material names are the project's);
* ``scale`` -> ``object.size`` (m), the up axis (after the rotations) -> ``object.up``;
* ``g`` -> the scene's gravity, turned into the project's +z-up world;
* a ``surface_collider`` facing up, or the floor of ``bounding_box``, -> the drop scene's ground
  (mode and friction) at the gap below the object that PhysGaussian has -> ``object.drop_height``;
* ``frame_dt`` -> ``output.fps``, ``frame_num`` -> ``output.frames`` (+1: the rest frame),
  ``opacity_threshold`` -> ``planner.min_opacity`` (exactly: ``planner.relative_opacity`` 0),
  ``particle_filling`` -> ``planner.fill_interior``.

Numerical settings the planner and the CFL stepping choose (``substep_dt``, ``n_grid``, ...) and
the viewer's camera keys have no effect and are listed in ``PhysGaussianRun.ignored``. Anything
that would change the physics but has no counterpart (a cuboid boundary condition, an impulse,
per-region materials, plasticity parameters other than the table's) raises
``PhysGaussianConfigError`` naming the key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from physgm.physics.materials import PhysicsSpec, get_material

# physgm's name for each of PhysGaussian's materials (mpm_solver_warp: jelly, metal, sand, foam,
# snow, plasticine): all six exist in the table, each with its own constitutive model.
MATERIALS = {
    "jelly": "jelly",
    "metal": "metal",
    "sand": "sand",
    "foam": "foam",
    "snow": "snow",
    "plasticine": "plasticine",
}
# PhysGaussian's defaults (utils/decode_param.py) for keys a config may leave out.
DEFAULTS = {
    "material": "jelly",
    "E": 1e5,
    "nu": 0.4,
    "density": 200.0,
    "frame_dt": 1e-2,
    "frame_num": 100,
    "opacity_threshold": 0.02,
    "scale": 1.0,
    "grid_lim": 2.0,
    "n_grid": 50,
    "grid_v_damping_scale": 1.1,
    "rpic_damping": 0.0,
    "pic_damping": 0.0,
    "mpm_space_vertical_upward_axis": [0, 0, 1],
}
BOX_PADDING_CELLS = 3  # its bounding_box stops particles this many cells inside the grid
IGNORED = {
    "substep_dt": "physgm's CFL stepping chooses the sub-step",
    "n_grid": "physgm's planner fits its grid to the object and the motion",
    "grid_lim": "physgm's planner fits its grid to the object and the motion",
    "friction_angle": "used only by PhysGaussian's sand",
    **{
        k: "the viewer's camera; set camera.azimuth_deg / camera.elevation_deg instead"
        for k in (
            "mpm_space_viewpoint_center",
            "default_camera_index",
            "show_hint",
            "init_azimuthm",
            "init_elevation",
            "init_radius",
            "move_camera",
            "delta_a",
            "delta_e",
            "delta_r",
        )
    },
}
PLASTICITY = ("yield_stress", "hardening", "xi", "plastic_viscosity", "softening")
UP_AXES = {"z": (0.0, 0.0, 1.0), "y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0)}  # file axis -> object.up
# The turn the pipeline gives a .ply with that object.up (physgm.pipeline.prepared_input.UP_ROTATIONS,
# repeated so that data does not import the pipeline; a test keeps them equal).
UP_ROTATIONS = {
    "z": np.eye(3),
    "y": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
    "-y": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
}


class PhysGaussianConfigError(ValueError):
    """A PhysGaussian config key that physgm cannot honour; the message names it."""


@dataclass(frozen=True)
class PhysGaussianRun:
    """What a PhysGaussian config asks for, in simulate.yaml's terms (SI, the project's +z-up world)."""

    physics: PhysicsSpec  # material (the project's name), E (Pa), nu, density (kg/m^3)
    size_m: float  # largest extent of the object
    up: str  # file axis pointing up: z | y | -y
    gravity: tuple[float, float, float]  # m/s^2, world (+z up)
    ground: dict | None  # the drop scene's ground {height, friction, mode}; None: no ground
    drop_height_m: float  # gap between the object's lowest point and the ground at t = 0
    fps: float
    frames: int  # including the rest frame
    min_opacity: float
    fill_interior: bool
    ignored: dict[str, str] = field(default_factory=dict)  # key -> why it has no effect

    def apply(self, raw: dict) -> dict:
        """``raw`` (simulate.yaml as a plain dict) with this run's settings in place (a copy)."""
        out = {**raw}
        p = self.physics
        out["physics"] = {
            **(raw.get("physics") or {}),
            "material": p.material,
            "E": p.E,
            "nu": p.nu,
            "density": p.density,
        }
        out["object"] = {
            **(raw.get("object") or {}),
            "size": self.size_m,
            "up": self.up,
            "drop_height": self.drop_height_m,
        }
        out["scene"] = "drop"
        out["scene_overrides"] = {
            **(raw.get("scene_overrides") or {}),
            "gravity": list(self.gravity),
            "ground": self.ground,
        }
        out["output"] = {**(raw.get("output") or {}), "fps": self.fps, "frames": self.frames}
        out["planner"] = {
            **(raw.get("planner") or {}),
            "min_opacity": self.min_opacity,
            "relative_opacity": 0.0,  # the config's threshold exactly, as PhysGaussian applies it
            "fill_interior": self.fill_interior,
        }
        return out


def _fail(key: str, message: str) -> None:
    raise PhysGaussianConfigError(f"PhysGaussian config: {key}: {message}")


def _vec(value: Any, key: str) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64) if isinstance(value, (list, tuple)) else np.zeros(0)
    if v.shape != (3,) or not np.isfinite(v).all():
        _fail(key, f"must be three numbers, got {value!r}")
    return v


def _num(cfg: dict, key: str) -> float:
    value = cfg.get(key, DEFAULTS.get(key))
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        _fail(key, f"must be a finite number, got {value!r}")
    return float(value)


def _rotation(cfg: dict) -> np.ndarray:
    """PhysGaussian's pre-rotation: R_k ... R_1 applied in list order (transformation_utils)."""
    degrees, axes = cfg.get("rotation_degree", []), cfg.get("rotation_axis", [])
    if not isinstance(degrees, list) or not isinstance(axes, list) or len(degrees) != len(axes):
        _fail("rotation_degree", "rotation_degree and rotation_axis must be lists of the same length")
    rot = np.eye(3)
    for deg, axis in zip(degrees, axes, strict=True):
        if axis not in (0, 1, 2):
            _fail("rotation_axis", f"axes are 0, 1 or 2, got {axis!r}")
        c, s = math.cos(math.radians(float(deg))), math.sin(math.radians(float(deg)))
        i, j = [(1, 2), (2, 0), (0, 1)][axis]  # the plane the rotation turns
        r = np.eye(3)
        r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
        rot = r @ rot
    return rot


def _up_axis(u_mpm: np.ndarray, rot: np.ndarray) -> str:
    u_file = rot.T @ u_mpm  # the file axis that the rotations turn into PhysGaussian's up
    for name, axis in UP_AXES.items():
        if np.allclose(u_file, axis, atol=1e-6):
            return name
    _fail(
        "mpm_space_vertical_upward_axis",
        f"after rotation_degree/rotation_axis, up is the file direction "
        f"{np.round(u_file, 4).tolist()}; physgm's object.up takes the file's z, y or -y axis: rotate the "
        "rotations so that one of these points up",
    )


def _floors(cfg: dict, u: np.ndarray, duration: float) -> list[tuple[float, dict, str]]:
    """Planes below the object that act as its ground: (height along up in MPM space, ground, key)."""
    floors, bcs = [], cfg.get("boundary_conditions", [])
    if not isinstance(bcs, list):
        _fail("boundary_conditions", "must be a list")
    for i, bc in enumerate(bcs):
        key = f"boundary_conditions[{i}]"
        kind = bc.get("type") if isinstance(bc, dict) else None
        if kind == "bounding_box":
            # Its walls stop outward motion BOX_PADDING_CELLS cells inside [0, grid_lim]^3, with no
            # friction: only the floor has a counterpart (physgm's side walls follow its grid).
            dx = _num(cfg, "grid_lim") / _num(cfg, "n_grid")
            low = float(np.minimum(u * _num(cfg, "grid_lim"), 0.0).sum())  # lowest corner along up
            floors.append(
                (low + BOX_PADDING_CELLS * dx, {"height": 0.0, "friction": 0.0, "mode": "slip"}, key)
            )
        elif kind == "surface_collider":
            n = _vec(bc.get("normal"), f"{key}.normal")
            if not np.allclose(n / max(np.linalg.norm(n), 1e-12), u, atol=1e-6):
                _fail(
                    f"{key}.normal",
                    f"{n.tolist()} is not the up axis {u.tolist()}; only a ground plane "
                    "facing up maps onto physgm's scenes",
                )
            if float(bc.get("start_time", 0.0)) > 0.0 or float(bc.get("end_time", 1e3)) < duration:
                _fail(f"{key}.start_time", "a ground that exists only part of the time has no counterpart")
            surface, friction = bc.get("surface", "sticky"), float(bc.get("friction", 0.0))
            if surface == "cut":
                _fail(f"{key}.surface", "'cut' has no counterpart in physgm")
            # sticky: nodes below stop; slip and others: Coulomb friction on the tangential velocity.
            mode = "sticky" if surface == "sticky" else ("slip" if friction == 0.0 else "separate")
            floors.append(
                (
                    float(_vec(bc.get("point"), f"{key}.point") @ u),
                    {"height": 0.0, "friction": friction, "mode": mode},
                    key,
                )
            )
        else:
            _fail(
                f"{key}.type",
                f"{kind!r} has no counterpart in physgm's scenes (drop onto a ground "
                "under gravity); remove it, or use scene=push / scene=stretch without this file",
            )
    return floors


def read_physgaussian(cfg: dict, means: np.ndarray, opacities: np.ndarray) -> PhysGaussianRun:
    """Map a PhysGaussian config onto simulate.yaml's settings.

    Args:
        cfg: the parsed config JSON.
        means: [N, 3] Gaussian centres of the .ply, in the file's frame.
        opacities: [N] Gaussian opacities in [0, 1].
    Raises:
        PhysGaussianConfigError: a key has no counterpart; the message names it.
    """
    known = (
        set(DEFAULTS)
        | set(IGNORED)
        | set(PLASTICITY)
        | {
            "g",
            "boundary_conditions",
            "rotation_degree",
            "rotation_axis",
            "particle_filling",
            "additional_material_params",
            "sim_area",
        }
    )
    for key in cfg:
        if key not in known:
            _fail(key, "unknown key (not in PhysGaussian's utils/decode_param.py)")
    material = cfg.get("material", DEFAULTS["material"])
    if material not in MATERIALS:
        _fail("material", f"{material!r} is not one of PhysGaussian's {', '.join(MATERIALS)}")
    ours = get_material(MATERIALS[material])
    ignored = {k: why for k, why in IGNORED.items() if k in cfg}
    for key in PLASTICITY:
        if key in cfg:
            _fail(
                key,
                f"physgm takes plasticity from its material table "
                f"(conf/sim/material/{ours.name}.yaml, "
                f"model {ours.model}); remove the key or edit that file",
            )
    if material == "sand" and "friction_angle" in cfg:
        ignored.pop("friction_angle")
        if not math.isclose(_num(cfg, "friction_angle"), ours.plasticity.get("friction_angle", math.nan)):
            _fail(
                "friction_angle",
                f"{cfg['friction_angle']} degrees differs from physgm's sand "
                f"({ours.plasticity.get('friction_angle')} degrees, conf/sim/material/sand.yaml); "
                "remove the key or edit that file",
            )
    if cfg.get("additional_material_params"):
        _fail(
            "additional_material_params",
            "per-region materials have no counterpart: physgm simulates one material per object",
        )
    if cfg.get("sim_area") is not None:
        _fail("sim_area", "simulating a cropped region has no counterpart; crop the .ply instead")
    if _num(cfg, "grid_v_damping_scale") < 1.0:
        _fail("grid_v_damping_scale", "grid velocity damping has no counterpart in physgm's scenes")
    for key in ("rpic_damping", "pic_damping"):
        if _num(cfg, key) != 0.0:
            _fail(key, "physgm's solver blends PIC and FLIP itself (conf/sim/solver/default.yaml: flip)")
    if "g" not in cfg:
        _fail("g", "missing; give gravity as [gx, gy, gz] in m/s^2 in PhysGaussian's MPM space")

    rot = _rotation(cfg)
    u = _vec(
        cfg.get("mpm_space_vertical_upward_axis", DEFAULTS["mpm_space_vertical_upward_axis"]),
        "mpm_space_vertical_upward_axis",
    )
    u = u / max(float(np.linalg.norm(u)), 1e-12)
    up = _up_axis(u, rot)
    to_world = UP_ROTATIONS[up] @ rot.T  # PhysGaussian's MPM axes -> the project's world axes
    gravity = tuple(float(c) for c in to_world @ _vec(cfg["g"], "g"))

    threshold = _num(cfg, "opacity_threshold")
    pts = np.asarray(means, dtype=np.float64)[np.asarray(opacities).reshape(-1) > threshold] @ rot.T
    if len(pts) == 0:
        _fail("opacity_threshold", f"no Gaussian of the .ply is more opaque than {threshold}")
    scale = _num(cfg, "scale")
    lo, hi = pts.min(0), pts.max(0)
    extent = float((hi - lo).max())
    if not (scale > 0 and extent > 0):
        _fail("scale", f"the object must have a positive size (scale {scale}, extent {extent:.3g})")
    # Its MPM-space positions: box centre at (1, 1, 1), largest extent `scale`; heights along up.
    bottom = float((((pts - (lo + hi) / 2) * (scale / extent) + 1.0) @ u).min())
    frame_dt, frame_num = _num(cfg, "frame_dt"), _num(cfg, "frame_num")
    if not (frame_dt > 0 and frame_num >= 1 and frame_num == int(frame_num)):
        _fail("frame_num", f"need frame_dt > 0 and a whole frame_num >= 1, got {frame_dt}, {frame_num}")
    floors = _floors(cfg, u, frame_dt * frame_num)
    for height, _, key in floors:
        if height > bottom + 1e-6 * scale:
            _fail(
                key,
                f"its plane (height {height:.4g} m along up) cuts through the object, whose lowest "
                f"point is at {bottom:.4g} m in PhysGaussian's MPM space",
            )
    ground, gap = None, 0.0
    if floors:
        height, ground, _ = max(floors, key=lambda f: f[0])  # the first plane the object meets
        gap = max(bottom - height, 0.0)
    try:
        physics = PhysicsSpec(ours.name, E=_num(cfg, "E"), nu=_num(cfg, "nu"), density=_num(cfg, "density"))
    except ValueError as err:  # E, nu or density outside what a simulation takes
        _fail("E, nu, density", str(err))
    return PhysGaussianRun(
        physics=physics,
        size_m=scale,
        up=up,
        gravity=gravity,
        ground=ground,
        drop_height_m=gap,
        fps=1.0 / frame_dt,
        frames=int(frame_num) + 1,  # noqa: E501
        min_opacity=threshold,
        fill_interior=cfg.get("particle_filling") is not None,
        ignored=ignored,
    )
