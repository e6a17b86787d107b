"""The DPO rollout environment: scenes with reference videos, and simulate / render / score one physics.

A scene is an asset with ``videos/<name>.mp4`` + ``.json``: the model's input views, the decoded
reference video, its camera and the generator's placement settings, and the true physics. One
physics guess is simulated with the project's Warp MPM (planner included) on the model's own
Gaussians, placed in the world exactly as the data generator placed the true object for the
reference video (``physgm.data.video.place_object`` with the video's settings), rendered from the
reference camera within a time budget (``physgm.train.rollout_budget``) and scored against the
reference (``physgm.metrics.clip_score``). Used by the rollout callback, ``evaluate_dpo`` and
``python -m physgm.bench dpo-landscape`` alike.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import torch

from physgm.cameras import Cameras
from physgm.data.datamodule import FolderRecord, example_rng
from physgm.data.format import load_asset, read_split
from physgm.data.video import VideoConfig, codec_round_trip, place_object, read_mp4, render_frames
from physgm.data.views import ViewConfig, build_example
from physgm.gaussians import Gaussians
from physgm.metrics.clip_score import ScoreConfig, score_clip
from physgm.model.posterior import PhysicsPosterior, PhysicsSample
from physgm.model.predict import predict_scene
from physgm.physics.materials import MATERIAL_NAMES, PhysicsSpec
from physgm.train.pairs import SceneInputs
from physgm.train.rollout_budget import BoundedRun, BudgetConfig, bounded_simulate


@dataclass
class SimSettings:
    """How one physics guess is simulated, rendered and scored (rollouts and evaluation)."""

    resolution: int | None = 64  # square render size, px (None: the reference video's own size)
    n_frames: int | None = 25  # frames incl. the rest frame (None: the whole reference video)
    backend: str = "warp"  # physgm.render backend
    planner: dict = field(default_factory=dict)  # PlannerConfig overrides; {} plans like the reference video
    solver: dict = field(default_factory=dict)  # SolverConfig overrides; frame_dt always = 1 / video fps
    device: str = "auto"  # Warp device of the MPM: "auto" follows the model (cpu / cuda:N)
    # Candidates go through the reference videos' H.264 encoding before scoring, so codec
    # artefacts cancel instead of moving tracks and landing frames (data.video.codec_round_trip).
    codec_round_trip: bool = True
    budget: BudgetConfig = field(default_factory=BudgetConfig)  # wall-clock limit per candidate
    score: ScoreConfig = field(default_factory=ScoreConfig)  # how a clip is compared with the reference

    def __post_init__(self) -> None:
        if isinstance(self.budget, dict):
            self.budget = BudgetConfig(**self.budget)
        if isinstance(self.score, dict):
            self.score = ScoreConfig(**self.score)


@dataclass
class RolloutScene:
    """A scene with a reference video: the model's inputs, the video and the true physics."""

    id: str
    index: int  # position in the split; decides the DDP rank that simulates it
    inputs: SceneInputs
    video_path: Path
    fps: float
    camera: Cameras  # [1] the reference camera at the video's resolution
    video: VideoConfig  # the generator's placement and scene settings (videos/<scene>.json "settings")
    material: str  # true (or, for real assets, annotated) material
    log10_E: float
    nu: float
    true_known: bool

    def truth(self) -> dict:
        """The scene's id and true physics: the first columns of every per-scene report row."""
        return {"scene": self.id, "material": self.material, "log10_E": self.log10_E, "nu": self.nu}


def load_scenes(
    root: str | Path,
    split: str,
    video_name: str = "drop",
    num_views: int = 4,
    input_resolution: int | None = None,
    background: float = 1.0,
    seed: int = 0,
    max_scenes: int | None = None,
) -> list[RolloutScene]:
    """Every asset of ``split`` that has the reference video ``videos/<video_name>.mp4``.

    Input views are the ones the datamodule serves for evaluation (fixed per asset).
    """
    root = Path(root)
    scenes: list[RolloutScene] = []
    skipped: list[str] = []
    centre_placed: list[str] = []
    view_cfg = ViewConfig(num_targets=4, input_resolution=input_resolution, background=background)
    for aid in read_split(root, split):
        asset = load_asset(root / aid)
        video = next((v for v in asset.videos if v.scene == video_name), None)
        if video is None:
            skipped.append(aid)
            continue
        meta = json.loads(video.path.with_suffix(".json").read_text())
        if meta.get("height_from") != "surface":
            centre_placed.append(aid)
        known = {f.name for f in fields(VideoConfig)}
        settings = {
            k: (tuple(v) if isinstance(v, list) else v)
            for k, v in meta.get("settings", {}).items()
            if k in known
        }
        ex = build_example(FolderRecord(asset), view_cfg, example_rng(aid, True, seed))
        inputs = SceneInputs(
            ex.input_images[:num_views],
            ex.input_masks[:num_views],
            ex.input_c2w[:num_views],
            ex.input_Ks[:num_views],
        )
        phys = asset.physical
        scenes.append(
            RolloutScene(
                aid,
                len(scenes),
                inputs,
                video.path,
                video.fps,
                video.cameras,
                VideoConfig(**settings),
                phys.material,
                math.log10(phys.E),
                phys.nu,
                phys.true_known,
            )
        )
        if max_scenes is not None and len(scenes) >= max_scenes:
            break
    if skipped:
        warnings.warn(
            f"{len(skipped)} asset(s) of split {split!r} have no videos/{video_name}.mp4 and are left out: "
            f"{skipped[:5]}",
            stacklevel=2,
        )
    if centre_placed:
        warnings.warn(
            f"{len(centre_placed)} reference video(s) of split {split!r} of {root} were simulated before "
            "drop heights were measured from the object's surface, so they start half a particle "
            "spacing lower than the rollouts compared with them; regenerate the data "
            f"(python -m physgm.data.synth) for rollouts that match: {centre_placed[:5]}",
            stacklevel=2,
        )
    if not scenes:
        raise ValueError(
            f"split {split!r} of {root} has no asset with a reference video videos/{video_name}.mp4; "
            "generate the data with --video-fraction > 0"
        )
    return scenes


def reference_frames(scene: RolloutScene, n_frames: int | None = None) -> np.ndarray:
    """The reference video as uint8 [T, H, W, 3], cut to ``n_frames``."""
    return read_mp4(scene.video_path, n_frames)


def render_camera(scene: RolloutScene, resolution: int | None) -> Cameras:
    """The reference camera, resized to ``resolution`` px (intrinsics scaled with the image)."""
    cam = scene.camera
    if resolution is None:
        return cam
    Ks = cam.Ks.clone()
    Ks[:, 0] *= resolution / cam.width
    Ks[:, 1] *= resolution / cam.height
    return Cameras(cam.c2w, Ks, resolution, resolution)


def predict(model: torch.nn.Module, inputs: SceneInputs) -> tuple[Gaussians, PhysicsPosterior]:
    """The model's Gaussians (asset frame, CPU) and physics posterior [1] for one scene."""
    pred = predict_scene(model, inputs.images, inputs.masks, inputs.c2w, inputs.Ks)
    return pred.gaussians, pred.posterior


def physics_spec(sample: PhysicsSample, k: int = 0) -> PhysicsSpec:
    """Candidate ``k`` of a [1, K] sample as simulator input (E and nu clipped to simulable values;
    the table's density)."""
    return PhysicsSpec(
        material=MATERIAL_NAMES[int(sample.material[0, k])],
        E=float(sample.youngs_modulus()[0, k]),
        nu=float(sample.poisson_ratio()[0, k]),
    )


@dataclass
class ClipResult:
    """One physics guess simulated like the reference video and scored against it."""

    distance: float | None  # the score (ScoreConfig); None: skipped, cut, or not finite
    mode: str = ""  # planner path: rigid / mpm
    E_used: float | None = None  # Pa, after any stiffness cap
    fallback: int = -1  # -1: planned as asked; i: BudgetConfig.fallbacks[i]
    predicted_error_px: float = 0.0  # the plan's error against full-stiffness MPM
    predicted_seconds: float = 0.0
    skipped: str | None = None  # why the candidate was not (fully) simulated
    terms: dict = field(default_factory=dict)  # the score's parts
    frames: np.ndarray | None = None  # [T, H, W, 3] uint8 as scored (kept only when asked for)


def simulate_clip(
    scene: RolloutScene,
    gaussians: Gaussians,
    physics: PhysicsSpec,
    settings: SimSettings,
    n_frames: int,
    device: str = "cpu",
    start: float | None = None,
) -> tuple[np.ndarray | None, BoundedRun]:
    """Simulate ``physics`` on ``gaussians`` (asset frame) like the reference video, within the budget.

    The object is placed with the video's own settings (``place_object``), dropped in the
    video's scene at the video's frame rate and rendered from the video's camera over the same
    background: frames [n_frames, H, W, 3] uint8 (None when the budget skipped or cut the run).
    """
    from physgm.sim.mpm.stepping import SolverConfig
    from physgm.sim.planner import PlannerConfig

    world, _ = place_object(gaussians, scene.video)
    camera = render_camera(scene, settings.resolution)
    solver = SolverConfig(**{**settings.solver, "frame_dt": 1.0 / scene.fps})
    # As write_reference_video does: every Gaussian carries mass (faint glass / jelly Gaussians too),
    # and explicit MPM for every candidate (no pressure split), so the candidates of a scene differ
    # only in their physics, never in the integrator the planner picks for their stiffness.
    planner = {"min_opacity": min(0.05, 0.5 * float(world.opacities.min())), "allow_pressure": False}
    # The planner's pixel bounds are measured at the output size; scaled with the render size they
    # stay the same length in metres, so a small render gets the reference video's plan.
    scale = camera.width / scene.camera.width
    if scale != 1.0:
        defaults = PlannerConfig()
        planner.update(
            bound_px=defaults.bound_px * scale,
            rest_px=defaults.rest_px * scale,
            rest_budget_px=defaults.rest_budget_px * scale,
        )
    planner.update(settings.planner)
    run = bounded_simulate(
        world,
        physics,
        scene.video.scene,
        camera,
        n_frames,
        planner,
        solver,
        {"height": scene.video.drop_height_m},
        device,
        settings.budget,
        start,
    )
    if run.trajectory is None:
        return None, run
    return render_frames(run.trajectory, camera, settings.backend, scene.video.background), run


def evaluate_physics(
    scene: RolloutScene,
    gaussians: Gaussians,
    physics: PhysicsSpec,
    reference: np.ndarray,
    settings: SimSettings,
    device: str = "cpu",
    keep_frames: bool = False,
) -> ClipResult:
    """Simulate ``physics`` on ``gaussians`` like the reference video (``simulate_clip``) and score the
    clip against ``reference`` [T, H, W, 3] uint8."""
    start = time.perf_counter()
    n_frames = settings.n_frames or len(reference)
    frames, run = simulate_clip(scene, gaussians, physics, settings, n_frames, device, start)
    result = ClipResult(
        None,
        fallback=run.fallback,
        predicted_error_px=run.predicted_error_px,
        predicted_seconds=run.predicted_seconds,
        skipped=run.skipped,
    )
    if frames is None:
        return result
    result.mode, result.E_used = str(run.trajectory.plan.mode), float(run.trajectory.plan.E_used)
    if settings.codec_round_trip:
        frames = codec_round_trip(frames, scene.fps)
    score = score_clip(reference[:n_frames], frames, settings.score)
    result.distance = score.value if math.isfinite(score.value) else None
    result.terms = score.terms
    result.frames = frames if keep_frames else None
    return result


def warp_device(setting: str, torch_device: torch.device) -> str:
    """The Warp device of a ``SimSettings.device`` value: "auto" follows the model."""
    if setting != "auto":
        return setting
    return "cpu" if torch_device.type != "cuda" else f"cuda:{torch_device.index or 0}"
