"""Reference drop videos: the asset's true physics, the project's MPM, the paper's camera.

The object (asset frame: radius 0.5, +z up) is scaled to metres by ``object_scale`` and placed
with its lowest point ``drop_height_m`` above the ground plane z = 0, then simulated by
``physgm.sim.gaussian_trajectory.simulate`` with the "drop" scene and rendered from azimuth -45 or 135
degrees, elevation 0, radius 1.8 m (the PhysGM evaluation camera), looking at the middle of
the vertical range the object can occupy. 50 frames at 25 fps go to ``videos/drop.mp4``;
``videos/drop.json`` holds everything needed to redo the simulation (camera, fps, frames,
object-to-world transform, scene) so DPO rollouts can be compared with it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from physgm.cameras import Cameras, orbit_cameras
from physgm.data.format import CAMERA_RADIUS, FOV_DEG
from physgm.data.priors import TruePhysics
from physgm.data.writer import camera_entry, write_json
from physgm.gaussians import Gaussians
from physgm.mp4 import read_mp4, write_mp4
from physgm.placement import place


@dataclass
class VideoConfig:
    """Reference video settings."""

    scene: str = "drop"  # registered scene (conf/sim/scene)
    n_frames: int = 50  # frames including the rest frame 0
    fps: float = 25.0
    azimuths_deg: tuple[float, ...] = (-45.0, 135.0)  # one is drawn per asset
    elevation_deg: float = 0.0
    radius_m: float = CAMERA_RADIUS
    fov_deg: float = FOV_DEG
    object_scale: float = 0.6  # m per asset-frame unit: objects are at most 0.6 m across
    drop_height_m: float = 0.25  # gap between the object's lowest point and the ground at t = 0
    background: float = 1.0  # white


def place_object(gaussians: Gaussians, cfg: VideoConfig) -> tuple[Gaussians, np.ndarray]:
    """Asset-frame Gaussians scaled and lifted into the simulation world, and the [4, 4] transform."""
    lowest = float(gaussians.means[:, 2].min())
    placed = place(gaussians, cfg.object_scale, (0.0, 0.0, lowest), (0.0, 0.0, cfg.drop_height_m))
    return placed.gaussians, placed.object_to_world


def video_camera(cfg: VideoConfig, azimuth_deg: float, resolution: int) -> Cameras:
    """The evaluation camera, aimed at the middle of [ground, top of the object at t = 0]."""
    top = cfg.drop_height_m + 2 * 0.5 * cfg.object_scale
    return orbit_cameras(
        [azimuth_deg],
        [cfg.elevation_deg],
        cfg.radius_m,
        cfg.fov_deg,
        resolution,
        resolution,
        target=(0.0, 0.0, top / 2),
    )


def render_frames(trajectory, camera: Cameras, backend: str, background: float) -> np.ndarray:
    """RGB uint8 frames [T, H, W, 3] of a simulated trajectory (``physgm.render.frames.Trajectory``)
    over a uniform grey ``background``, as the reference videos are drawn.

    Raises:
        ValueError: the trajectory holds non-finite Gaussians (a reference must not be a black clip).
    """
    from physgm.render import Renderer
    from physgm.render.frames import Shot, render_trajectory

    frames, finite = render_trajectory(
        trajectory, Shot(camera, Renderer(backend=backend), np.full(3, background))
    )
    if not finite:
        raise ValueError("the simulated trajectory has non-finite Gaussians; its frames would be black")
    return frames


def codec_round_trip(frames: np.ndarray, fps: float) -> np.ndarray:
    """``frames`` [T, H, W, 3] uint8 after the reference videos' H.264 encoding and decoding.

    Scoring a raw render against a decoded reference lets codec artefacts move the tracks and
    the landing frame: the exact re-simulation of a reference scored 0.14 raw and 0.006 after
    this round trip (python -m physgm.bench dpo-landscape, jelly syn_000001).
    """
    import tempfile

    with tempfile.TemporaryDirectory(prefix="physgm-codec-") as tmp:
        path = Path(tmp) / "clip.mp4"
        write_mp4(path, frames, fps)
        return read_mp4(path)


def write_reference_video(
    folder: Path,
    gaussians: Gaussians,
    physics: TruePhysics,
    rng: np.random.Generator,
    resolution: int,
    backend: str = "warp",
    cfg: VideoConfig | None = None,
) -> dict:
    """Simulate, render and write ``videos/<scene>.mp4`` + ``.json`` into an asset folder."""
    from physgm.physics.materials import PhysicsSpec
    from physgm.sim.gaussian_trajectory import simulate
    from physgm.sim.mpm.stepping import SolverConfig

    cfg = cfg or VideoConfig()
    az = float(cfg.azimuths_deg[int(rng.integers(len(cfg.azimuths_deg)))])
    world, T = place_object(gaussians, cfg)
    camera = video_camera(cfg, az, resolution)
    # Translucent glass and jelly are drawn with very faint Gaussians (opacity ~0.02); the
    # planner's default would treat them as empty space, so every Gaussian carries mass here.
    # Explicit MPM throughout (no pressure split), as stage 2's rollouts against these videos.
    min_opacity = min(0.05, 0.5 * float(world.opacities.min()))
    traj = simulate(
        world,
        PhysicsSpec(physics.material, physics.E, physics.nu, physics.density),
        cfg.scene,
        camera,
        n_frames=cfg.n_frames,
        planner={"min_opacity": min_opacity, "allow_pressure": False},
        solver=SolverConfig(frame_dt=1.0 / cfg.fps),
        scene_overrides={"height": cfg.drop_height_m},
    )
    frames = render_frames(traj, camera, backend, cfg.background)
    vdir = folder / "videos"
    vdir.mkdir(parents=True, exist_ok=True)
    write_mp4(vdir / f"{cfg.scene}.mp4", frames, cfg.fps)
    plan = getattr(traj, "plan", None)
    meta = {
        "scene": cfg.scene,
        "fps": cfg.fps,
        "frames": int(len(frames)),
        "camera": camera_entry(camera.c2w[0], camera.Ks[0], camera.width, camera.height),
        "azimuth_deg": az,
        "elevation_deg": cfg.elevation_deg,
        "radius_m": cfg.radius_m,
        "object_to_world": T.tolist(),
        "ground_height_m": 0.0,
        # The drop height is from the ground to the material's lowest surface (physgm.sim.scenes);
        # videos without this key were placed by the lowest particle centres, half a spacing lower.
        "height_from": "surface",
        "settings": asdict(cfg),
        "physics": {
            "material": physics.material,
            "E": physics.E,
            "nu": physics.nu,
            "density": physics.density,
        },
        "simulation": {
            "mode": str(getattr(plan, "mode", "")),
            "integrator": str(getattr(plan, "integrator", "explicit")),
            "E_used": float(getattr(plan, "E_used", physics.E)),
            "substeps": int(getattr(traj, "substeps", 0)),
        },
    }
    write_json(vdir / f"{cfg.scene}.json", meta)
    return {"seconds_sim": float(getattr(traj, "seconds", 0.0)), **meta["simulation"]}
