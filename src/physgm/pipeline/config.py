"""Typed settings of one ``simulate.py`` run, read from the Hydra config (conf/simulate.yaml).

Every value a user can mistype is checked here, before any work starts, so a bad setting stops
with one line saying which key was wrong and what it accepts.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from physgm.errors import UserError

log = logging.getLogger(__name__)
DEFAULT_CKPT = "checkpoints/physgm_tiny.ckpt"
UP_AXES = ("z", "y", "-y")


@dataclass
class PhysicsOverrides:
    """Physics the user fixed; None means "use the prediction"."""

    material: str | None = None
    E: float | None = None  # Pa
    nu: float | None = None
    density: float | None = None  # kg/m^3
    samples: int = 0  # K extra futures drawn from the posterior


@dataclass
class CameraSettings:
    """Output camera; None angles follow the input view."""

    azimuth_deg: float | None = None
    elevation_deg: float | None = None
    fov_deg: float = 34.0  # horizontal
    margin: float = 1.15  # the motion region fills 1 / margin of the frame


@dataclass
class OutputSettings:
    resolution: int = 256  # px, square
    frames: int = 50  # T including frame 0
    fps: float = 25.0
    gif: bool = False
    frame_plys: bool = False
    keyframes: int = 5
    floor: bool = True
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    progress: bool = True


@dataclass
class RunConfig:
    """One run: where the input is, what to simulate, where the outputs go."""

    input: Path
    output_dir: Path
    mask: Path | None = None
    ckpt: Path = Path(DEFAULT_CKPT)
    device: str = "cpu"
    seed: int = 0
    torch_threads: int = 1  # torch intra-op threads during the run; 0 keeps torch's default
    scene: str = "drop"
    scene_overrides: dict[str, Any] = field(default_factory=dict)
    physics: PhysicsOverrides = field(default_factory=PhysicsOverrides)
    size_m: float = 0.2  # object's largest extent
    drop_height_m: float | None = 0.1
    stand: bool = True  # cut a photographed object's underside flat when it would not stand (standing.py)
    up: str = "z"
    camera: CameraSettings = field(default_factory=CameraSettings)
    output: OutputSettings = field(default_factory=OutputSettings)
    renderer: dict[str, Any] = field(default_factory=lambda: {"backend": "warp"})
    planner: dict[str, Any] = field(default_factory=dict)
    solver: dict[str, Any] = field(default_factory=dict)
    max_sim_minutes: float | None = 10.0  # the plans' predicted simulation time a CPU run may take

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        from physgm.physics.materials import MATERIAL_NAMES
        from physgm.sim.scenes import SCENES

        p, o, c = self.physics, self.output, self.camera
        if self.scene not in SCENES or self.scene == "two_objects":
            names = ", ".join(s for s in SCENES if s != "two_objects")
            raise UserError(f"scene={self.scene!r} is not a single-object scene; choose one of: {names}")
        if p.material is not None and p.material not in MATERIAL_NAMES:
            raise UserError(
                f"physics.material={p.material!r} is unknown; choose one of: {', '.join(MATERIAL_NAMES)}"
            )
        _check(
            p.E is None or (math.isfinite(p.E) and p.E > 0),
            f"physics.E={p.E!r} must be a positive number of pascals",
        )
        _check(p.nu is None or -1.0 < p.nu < 0.5, f"physics.nu={p.nu!r} must be in (-1, 0.5)")
        _check(
            p.density is None or (math.isfinite(p.density) and p.density > 0),
            f"physics.density={p.density!r} must be a positive number (kg/m^3)",
        )
        _check(0 <= p.samples <= 64, f"physics.samples={p.samples!r} must be an integer in [0, 64]")
        _check(
            math.isfinite(self.size_m) and 1e-3 <= self.size_m <= 10.0,
            f"object.size={self.size_m!r} must be in [0.001, 10] m",
        )
        _check(
            self.drop_height_m is None
            or (math.isfinite(self.drop_height_m) and 0 <= self.drop_height_m <= 10),
            f"object.drop_height={self.drop_height_m!r} must be in [0, 10] m",
        )
        _check(self.up in UP_AXES, f"object.up={self.up!r} must be one of {', '.join(UP_AXES)}")
        _check(
            16 <= o.resolution <= 4096 and o.resolution % 2 == 0,
            f"output.resolution={o.resolution!r} must be an even number of pixels in [16, 4096]",
        )
        _check(2 <= o.frames <= 10000, f"output.frames={o.frames!r} must be in [2, 10000]")
        _check(math.isfinite(o.fps) and 1 <= o.fps <= 240, f"output.fps={o.fps!r} must be in [1, 240]")
        _check(1 <= o.keyframes <= 16, f"output.keyframes={o.keyframes!r} must be in [1, 16]")
        _check(
            len(o.background) == 3 and all(0 <= v <= 1 for v in o.background),
            f"output.background={list(o.background)!r} must be three numbers in [0, 1]",
        )
        _check(0 < c.fov_deg < 170, f"camera.fov_deg={c.fov_deg!r} must be in (0, 170)")
        _check(c.margin >= 1.0, f"camera.margin={c.margin!r} must be >= 1")
        _check(
            c.elevation_deg is None or -89 <= c.elevation_deg <= 89,
            f"camera.elevation_deg={c.elevation_deg!r} must be in [-89, 89]",
        )
        _check(
            self.max_sim_minutes is None
            or (math.isfinite(self.max_sim_minutes) and self.max_sim_minutes > 0),
            f"max_sim_minutes={self.max_sim_minutes!r} must be a positive number of minutes, or null "
            "for no limit",
        )
        _check(0 <= self.torch_threads <= 256, f"torch_threads={self.torch_threads!r} must be in [0, 256]")
        _check(
            self.device == "cpu" or self.device.startswith("cuda"),
            f"device={self.device!r} must be cpu or cuda[:N]",
        )


def _check(ok: bool, message: str) -> None:
    if not ok:
        raise UserError(message)


def _number(value: Any, key: str, kind=float) -> Any:
    if value is None:
        return None
    if isinstance(value, bool):
        raise UserError(f"{key}={value!r} must be a number")
    try:
        out = kind(value)
    except (TypeError, ValueError):
        raise UserError(f"{key}={value!r} must be a number") from None
    if kind is int and out != float(value):
        raise UserError(f"{key}={value!r} must be an integer")
    return out


def _flag(value: Any, key: str) -> bool:
    """A true/false setting; anything else (``output.gif=maybe``, ``object.stand=1``) is an error."""
    if not isinstance(value, bool):
        raise UserError(f"{key}={value!r} must be true or false")
    return value


def _with_physgaussian(raw: dict) -> dict:
    """``raw`` with a PhysGaussian simulation config's settings in place (docs/interop.md).

    The file's values replace simulate.yaml's; a ``physics.*`` override given on the command line
    that disagrees with the file is an error rather than a silent choice.
    """
    from physgm.data.readers.physgaussian import PhysGaussianConfigError, read_physgaussian
    from physgm.gaussians import read_ply

    path = Path(str(raw["physgaussian_config"])).expanduser()
    source = Path(str(raw.get("input") or ""))
    if source.suffix.lower() != ".ply":
        raise UserError(
            f"physgaussian_config={path} goes with a 3DGS .ply input (PhysGaussian's), got input={source}"
        )
    try:
        pg = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise UserError(f"physgaussian_config={path} is not a readable JSON file ({err})") from None
    if not isinstance(pg, dict):
        raise UserError(f"physgaussian_config={path} must hold a JSON object")
    try:
        g = read_ply(source, keep_sh=False)
    except (OSError, ValueError, KeyError) as err:
        raise UserError(f"input={source} is not a readable 3DGS .ply ({err})") from None
    try:
        run = read_physgaussian(pg, g.means.double().numpy(), g.opacities.double().numpy())
    except PhysGaussianConfigError as err:
        raise UserError(f"{path}: {err}") from None
    given = raw.get("physics") or {}
    for key in ("material", "E", "nu", "density"):
        mine, theirs = given.get(key), getattr(run.physics, key)
        if mine is not None and mine != theirs:
            raise UserError(
                f"physics.{key}={mine!r} disagrees with {path} ({key} = {theirs!r}); change one of them"
            )
    for key, why in run.ignored.items():
        log.info("physgaussian_config: %s has no effect here: %s", key, why)
    return run.apply(raw)


@dataclass(frozen=True)
class SceneSettings:
    """The scene's settings (conf/sim/scene/<name>.yaml with the user's changes), read once per run."""

    settings: dict[str, Any]  # every setting of the scene, as simulated
    overrides: dict[str, Any]  # the part that differs from the scene file, handed to the simulator

    @property
    def ground_height(self) -> float | None:
        """Height of the ground plane, m (None: the scene has no ground)."""
        ground = self.settings.get("ground")
        return None if ground is None else float(ground.get("height", 0.0))

    def facing(self, view: Any, extent: Any = None) -> SceneSettings:
        """These settings seen along ``view`` [3] (unit, object -> output camera): a stretch or push
        along the line of sight would be invisible, so unless the user set ``axis`` the horizontal
        world axis most across the view is used. A scene without a ground (the stretch) has nothing
        below the body, so it takes the vertical instead for a body taller than that (``extent``
        [3], m, its size along x, y, z), as long as the camera is not looking down on it (the
        vertical at least 60 degrees from the line of sight)."""
        if "axis" not in self.settings or "axis" in self.overrides:
            return self
        axis = min((0, 1), key=lambda a: abs(float(view[a])))
        upright = extent is not None and float(extent[2]) > float(extent[axis])
        if self.ground_height is None and upright and abs(float(view[2])) < 0.5:
            axis = 2
        return SceneSettings({**self.settings, "axis": axis}, {**self.overrides, "axis": axis})


def scene_settings(cfg: RunConfig) -> SceneSettings:
    """The run's scene settings; a setting the scene does not have is an error that lists its
    settings, and a value the scene refuses is an error too, both before any model loads."""
    import numpy as np

    from physgm.sim.scenes import build_scene, load_scene_config

    base = load_scene_config(cfg.scene)
    overrides = dict(cfg.scene_overrides)
    if cfg.scene == "drop" and cfg.drop_height_m is not None:
        overrides.setdefault("height", cfg.drop_height_m)
    unknown = sorted(set(overrides) - set(base))
    if unknown:
        raise UserError(f"scene {cfg.scene!r} has no setting(s) {unknown}; its settings are {sorted(base)}")
    # The scene built on a 3 x 3 x 3 lattice (materials 0 and 1, for two_objects) checks the values.
    probe = np.stack(np.meshgrid(*[np.linspace(-0.5, 0.5, 3)] * 3, indexing="ij"), -1).reshape(-1, 3)
    try:
        build_scene(cfg.scene, probe, np.arange(len(probe)) % 2, **overrides)
    except (ValueError, TypeError) as err:
        raise UserError(f"scene {cfg.scene!r}: {err}") from None
    return SceneSettings({**base, **overrides}, overrides)


def from_hydra(cfg: DictConfig) -> RunConfig:
    """The typed run settings of a composed ``conf/simulate.yaml``."""
    try:
        raw = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    except MissingMandatoryValue as err:
        key = getattr(err, "full_key", "input")
        raise UserError(f"{key} is required, e.g. `python simulate.py input=photo.png`") from None
    if raw.get("physgaussian_config") not in (None, ""):
        raw = _with_physgaussian(raw)
    phys, obj, cam, out = (
        raw.get("physics") or {},
        raw.get("object") or {},
        raw.get("camera") or {},
        raw.get("output") or {},
    )
    renderer = {k: v for k, v in (raw.get("renderer") or {}).items() if not k.startswith("_")}
    output_dir = (raw.get("paths") or {}).get("output_dir")
    if raw.get("input") in (None, ""):
        raise UserError("input is required, e.g. `python simulate.py input=photo.png`")
    if not output_dir:
        raise UserError("paths.output_dir is empty; give the run folder, e.g. paths.output_dir=outputs/run1")
    return RunConfig(
        input=Path(str(raw["input"])).expanduser(),
        output_dir=Path(str(output_dir)).expanduser(),
        mask=None if raw.get("mask") in (None, "") else Path(str(raw["mask"])).expanduser(),
        ckpt=Path(str(raw.get("ckpt") or DEFAULT_CKPT)).expanduser(),
        device=str(raw.get("device", "cpu")),
        seed=_number(raw.get("seed", 0), "seed", int),
        torch_threads=_number(raw.get("torch_threads", 1), "torch_threads", int),
        scene=str(raw.get("scene", "drop")),
        scene_overrides=dict(raw.get("scene_overrides") or {}),
        physics=PhysicsOverrides(
            material=None if phys.get("material") is None else str(phys["material"]),
            E=_number(phys.get("E"), "physics.E"),
            nu=_number(phys.get("nu"), "physics.nu"),
            density=_number(phys.get("density"), "physics.density"),
            samples=_number(phys.get("samples", 0), "physics.samples", int),
        ),
        size_m=_number(obj.get("size", 0.2), "object.size"),
        drop_height_m=_number(obj.get("drop_height", 0.1), "object.drop_height"),
        stand=_flag(obj.get("stand", True), "object.stand"),
        up=str(obj.get("up", "z")),
        camera=CameraSettings(
            azimuth_deg=_number(cam.get("azimuth_deg"), "camera.azimuth_deg"),
            elevation_deg=_number(cam.get("elevation_deg"), "camera.elevation_deg"),
            fov_deg=_number(cam.get("fov_deg", 34.0), "camera.fov_deg"),
            margin=_number(cam.get("margin", 1.15), "camera.margin"),
        ),
        output=OutputSettings(
            resolution=_number(out.get("resolution", 256), "output.resolution", int),
            frames=_number(out.get("frames", 50), "output.frames", int),
            fps=_number(out.get("fps", 25), "output.fps"),
            gif=_flag(out.get("gif", False), "output.gif"),
            frame_plys=_flag(out.get("frame_plys", False), "output.frame_plys"),
            keyframes=_number(out.get("keyframes", 5), "output.keyframes", int),
            floor=_flag(out.get("floor", True), "output.floor"),
            background=tuple(_number(v, "output.background") for v in out.get("background", (1.0, 1.0, 1.0))),
            progress=_flag(out.get("progress", True), "output.progress"),
        ),
        renderer=renderer or {"backend": "warp"},
        planner=dict(raw.get("planner") or {}),
        solver=dict(raw.get("solver") or {}),
        max_sim_minutes=_number(raw.get("max_sim_minutes", 10.0), "max_sim_minutes"),
    )
