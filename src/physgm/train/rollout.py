"""DPO rollouts: sample physics from the policy, simulate, render, score against reference videos.

For each scene of the DPO split (assets with ``videos/<scene>.mp4`` + ``.json``), the policy
predicts Gaussians and a physics posterior from the asset's input views; K candidates are drawn
from the posterior, each is simulated with the project's Warp MPM (planner included) on the
model's own Gaussians, placed in the world exactly as the data generator placed the true object
for the reference video (``physgm.data.video.place_object`` with the video's settings), rendered
from the reference camera and scored with ``physgm.metrics.trajectory.score_videos``. The lowest
distance wins, the highest loses (``physgm.train.pairs``).

``RolloutCallback`` does this once per refresh round and hands the DPO stage its dataloader.
Under DDP each rank simulates the scenes with ``index % world_size == rank``; the records are
gathered so every rank holds every pair, and Lightning's distributed sampler splits the pairs.
"""

from __future__ import annotations

import json
import math
import time
import warnings
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader

from physgm.cameras import Cameras
from physgm.data.datamodule import FolderRecord, example_rng
from physgm.data.format import load_asset, read_split
from physgm.data.video import VideoConfig, codec_round_trip, place_object, read_mp4, render_frames
from physgm.data.views import ViewConfig, build_example
from physgm.gaussians import Gaussians
from physgm.metrics.trajectory import score_videos
from physgm.model.posterior import LOG10_E_RANGE, NU_RANGE, PhysicsPosterior, PhysicsSample
from physgm.physics.materials import MATERIAL_NAMES
from physgm.train.pairs import (
    Candidate,
    PairCache,
    PairDataset,
    SceneInputs,
    SceneRecord,
    collate_pairs,
    gather_records,
    policy_fingerprint,
    round_stats,
    select_pair,
    settings_hash,
)
from physgm.warp_runtime import preload


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
    view_cfg = ViewConfig(num_targets=4, input_resolution=input_resolution, background=background)
    for aid in read_split(root, split):
        asset = load_asset(root / aid)
        video = next((v for v in asset.videos if v.scene == video_name), None)
        if video is None:
            skipped.append(aid)
            continue
        meta = json.loads(video.path.with_suffix(".json").read_text())
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
    device = next(model.parameters()).device
    modes = {m: m.training for m in model.modules()}  # restored one by one: frozen parts stay in eval
    model.eval()
    try:
        with torch.no_grad():
            out = model(
                inputs.images[None].to(device),
                inputs.masks[None].to(device),
                inputs.c2w[None].to(device),
                inputs.Ks[None].to(device),
            )
    finally:
        for m, mode in modes.items():
            m.training = mode
    g = out.gaussians.to_gaussians(0)
    g = Gaussians(
        g.means.float().cpu(),
        g.quats.float().cpu(),
        g.scales.float().cpu(),
        g.opacities.float().cpu(),
        g.colors.float().cpu(),
    )
    return g, out.physics.detach()


def physics_dict(sample: PhysicsSample, k: int = 0) -> dict:
    """Candidate ``k`` of a [1, K] sample as simulator input (E and nu clipped to simulable values)."""
    return {
        "material": MATERIAL_NAMES[int(sample.material[0, k])],
        "E": float(sample.youngs_modulus()[0, k]),
        "nu": float(sample.poisson_ratio()[0, k]),
    }


def simulate_clip(
    scene: RolloutScene,
    gaussians: Gaussians,
    physics: dict,
    settings: SimSettings,
    n_frames: int,
    device: str = "cpu",
) -> tuple[np.ndarray, dict]:
    """Simulate ``physics`` on ``gaussians`` (asset frame) like the reference video; returns (frames, info).

    The object is placed with the video's own settings (``place_object``), dropped in the
    video's scene at the video's frame rate and rendered from the video's camera over the same
    background: frames [n_frames, H, W, 3] uint8, info {mode, E_used} of the plan.
    """
    from physgm.sim.gaussian_trajectory import simulate
    from physgm.sim.planner import PlannerConfig
    from physgm.sim.stepping import SolverConfig

    world, _ = place_object(gaussians, scene.video)
    camera = render_camera(scene, settings.resolution)
    solver = SolverConfig(**{**settings.solver, "frame_dt": 1.0 / scene.fps})
    # As write_reference_video does: every Gaussian carries mass (faint glass / jelly Gaussians too).
    planner = {"min_opacity": min(0.05, 0.5 * float(world.opacities.min()))}
    # The planner's pixel bounds are measured at the output size; scaled with the render size they
    # stay the same length in metres, so a small render gets the reference video's plan.
    scale = camera.width / scene.camera.width
    if scale != 1.0:
        defaults = PlannerConfig()
        planner.update(bound_px=defaults.bound_px * scale, rest_px=defaults.rest_px * scale)
    planner.update(settings.planner)
    traj = simulate(
        world,
        physics,
        scene.video.scene,
        camera,
        n_frames=n_frames,
        planner=planner,
        solver=solver,
        scene_overrides={"height": scene.video.drop_height_m},
        device=device,
    )
    frames = render_frames(traj, camera, settings.backend, scene.video.background)
    return frames, {"mode": str(traj.plan.mode), "E_used": float(traj.plan.E_used)}


def evaluate_physics(
    scene: RolloutScene,
    gaussians: Gaussians,
    physics: dict,
    reference: np.ndarray,
    settings: SimSettings,
    device: str = "cpu",
) -> tuple[float, dict]:
    """Simulate ``physics`` on ``gaussians`` like the reference video (``simulate_clip``) and score the
    clip against ``reference`` [T, H, W, 3] uint8; returns (distance, info)."""
    n_frames = settings.n_frames or len(reference)
    frames, info = simulate_clip(scene, gaussians, physics, settings, n_frames, device)
    if settings.codec_round_trip:
        frames = codec_round_trip(frames, scene.fps)
    score = score_videos(reference[:n_frames], frames)
    return score.distance, info


def widen(posterior: PhysicsPosterior, min_std_decades: float, min_std_nu: float) -> PhysicsPosterior:
    """The posterior with its E and nu standard deviations floored (the exploration proposal)."""
    z_per_decade = 2.0 / (LOG10_E_RANGE[1] - LOG10_E_RANGE[0])
    z_per_nu = 2.0 / (NU_RANGE[1] - NU_RANGE[0])
    floor_E = 2.0 * math.log(max(min_std_decades * z_per_decade, 1e-12))
    floor_nu = 2.0 * math.log(max(min_std_nu * z_per_nu, 1e-12))
    return PhysicsPosterior(
        posterior.material_logits,
        posterior.z_E_mean,
        posterior.z_E_logvar.clamp_min(floor_E),
        posterior.z_nu_mean,
        posterior.z_nu_logvar.clamp_min(floor_nu),
    )


def scene_generator(seed: int, round_: int, scene: str) -> torch.Generator:
    """The same candidates for a scene and round whatever the rank count or restart."""
    return torch.Generator().manual_seed(
        (seed * 1_000_003 + round_ * 10_007 + zlib.crc32(scene.encode())) % 2**63
    )


@dataclass
class RolloutConfig:
    """Rollout settings (``stage.rollout`` in conf/stage/dpo.yaml)."""

    data_root: str | None = None  # PhysAssets root; fit() fills it from cfg.data.root
    split: str = "dpo"
    video_name: str = "drop"  # reference video videos/<name>.mp4
    num_views: int = 4  # input views the policy sees (rollouts and training)
    input_resolution: int | None = None  # px; fit() fills it from cfg.data.input_resolution
    background: float = 1.0
    seed: int = 0
    max_scenes: int | None = None  # use only the first N scenes of the split
    num_candidates: int = 3  # K physics samples per scene and round
    material: str = (
        "sample"  # "sample": candidates draw the material too; "mode": all use the most likely one
    )
    refresh_every_n_epochs: int = 4  # new rollouts (a new round) every N epochs
    min_std_decades: float = 0.3  # exploration floor: candidates' log10 E std is at least this
    min_std_nu: float = 0.03  # and nu's std at least this
    min_gap: float = 0.002  # best and worst closer than this (box units) is a tie: no pair
    anchor_ties: bool = False  # serve tie scenes too, for the KL anchor (loss.kl_weight)
    max_failed_fraction: float = 0.5  # more failed rollouts than this in a round stops training
    workers: int = 2  # candidates simulated at once (threads; Warp releases the GIL)
    batch_size: int = 8  # pairs per training batch (per device)
    num_workers: int = 0  # DataLoader workers
    cache_dir: str = "pairs"  # the pair cache (one folder per round)
    sim: SimSettings = field(default_factory=SimSettings)

    def __post_init__(self) -> None:
        if isinstance(self.sim, dict):
            self.sim = SimSettings(**self.sim)
        if self.material not in ("sample", "mode"):
            raise ValueError(f"rollout.material must be 'sample' or 'mode', got {self.material!r}")
        if (
            self.num_candidates < 2
            or self.refresh_every_n_epochs < 1
            or self.batch_size < 1
            or self.workers < 1
        ):
            raise ValueError(
                "rollout needs num_candidates >= 2, refresh_every_n_epochs >= 1, batch_size >= 1 and "
                f"workers >= 1; got {self.num_candidates}, {self.refresh_every_n_epochs}, "
                f"{self.batch_size}, {self.workers}"
            )


def rollout_scene(
    model: torch.nn.Module,
    scene: RolloutScene,
    cfg: RolloutConfig,
    round_: int,
    settings: str,
    policy: str = "",
    global_step: int = 0,
) -> SceneRecord:
    """Sample K candidates for one scene, simulate and score each, pick the pair."""
    gaussians, posterior = predict(model, scene.inputs)
    proposal = widen(_cpu(posterior), cfg.min_std_decades, cfg.min_std_nu)
    draws = proposal.sample(cfg.num_candidates, scene_generator(cfg.seed, round_, scene.id))
    if cfg.material == "mode":  # pairs then isolate E and nu: the material terms cancel in the DPO ratio
        draws = PhysicsSample(
            proposal.material_logits.argmax(-1, keepdim=True).expand_as(draws.material).clone(),
            draws.log10_E,
            draws.nu,
        )
    reference = reference_frames(scene, cfg.sim.n_frames)
    device = _warp_device(cfg.sim.device, next(model.parameters()).device)

    def run(k: int) -> Candidate:
        physics = physics_dict(draws, k)
        cand = Candidate(
            int(draws.material[0, k]),
            physics["material"],
            float(draws.log10_E[0, k]),
            float(draws.nu[0, k]),
            None,
        )
        start = time.perf_counter()
        try:
            distance, info = evaluate_physics(scene, gaussians, physics, reference, cfg.sim, device)
            cand.distance = float(distance) if math.isfinite(distance) else None
            cand.mode = info.get("mode", "")
            if cand.distance is None:
                cand.error = "trajectory distance is not finite (object lost by the tracker)"
        except (ValueError, RuntimeError) as err:  # e.g. SimulationDiverged, unsimulable physics
            cand.error = f"{type(err).__name__}: {err}"
        cand.seconds = time.perf_counter() - start
        return cand

    if cfg.workers > 1:
        preload(device)  # no Warp module may load while the workers launch kernels
        with ThreadPoolExecutor(cfg.workers, thread_name_prefix="physgm-rollout") as pool:
            candidates = list(pool.map(run, range(cfg.num_candidates)))
    else:
        candidates = [run(k) for k in range(cfg.num_candidates)]
    winner, loser, note = select_pair(candidates, cfg.min_gap)
    return SceneRecord(
        scene.id, scene.index, round_, settings, policy, candidates, winner, loser, global_step, note
    )


def _cpu(p: PhysicsPosterior) -> PhysicsPosterior:
    return PhysicsPosterior(*(getattr(p, f.name).float().cpu() for f in fields(p)))


def _warp_device(setting: str, torch_device: torch.device) -> str:
    if setting != "auto":
        return setting
    return "cpu" if torch_device.type != "cuda" else f"cuda:{torch_device.index or 0}"


class RolloutCallback(L.Callback):
    """Owns the DPO pairs: rolls out every ``refresh_every_n_epochs`` and serves the dataloader.

    Lightning asks ``LitDPO.train_dataloader`` for data at every epoch start (the DPO trainer
    reloads dataloaders every epoch), after a resumed run has restored its epoch; that call
    lands in ``train_dataloader`` here, which rolls out when the round changed.

    A cached scene is reused only for the same round, rollout settings and policy weights (a
    fingerprint taken at the round's start and kept in the checkpoint, so a run resumed in the
    middle of a round still finds its pairs, while a fresh run in an old folder does not reuse
    pairs drawn from another policy).
    """

    def __init__(self, **config) -> None:
        super().__init__()
        self.cfg = RolloutConfig(**config)
        self.scenes: list[RolloutScene] = []
        self.records: list[SceneRecord] = []
        self.round: int | None = None
        self.policy: str | None = None  # fingerprint of the policy at the start of self.round
        self._restored: dict = {}

    def state_dict(self) -> dict:
        return {"round": self.round, "policy": self.policy}

    def load_state_dict(self, state_dict: dict) -> None:
        self._restored = dict(state_dict)

    @property
    def settings(self) -> str:
        """Hash of everything that changes a rollout (not batch sizes or worker counts)."""
        c = asdict(self.cfg)
        for k in (
            "workers",
            "batch_size",
            "num_workers",
            "refresh_every_n_epochs",
            "max_failed_fraction",
            "cache_dir",
            "data_root",
        ):
            c.pop(k)
        return settings_hash(c)

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage == "fit" and not self.scenes:
            if not self.cfg.data_root:
                raise ValueError(
                    "the rollout callback needs data_root (stage.rollout.data_root or data.root)"
                )
            limit = self.cfg.max_scenes
            dev_run = getattr(trainer, "fast_dev_run", False)  # no trainer when called outside a fit
            if dev_run:  # it trains int(fast_dev_run) batches: roll out only the scenes they hold
                needed = int(dev_run) * self.cfg.batch_size * trainer.world_size
                limit = min(limit or needed, needed)
            self.scenes = load_scenes(
                self.cfg.data_root,
                self.cfg.split,
                self.cfg.video_name,
                self.cfg.num_views,
                self.cfg.input_resolution,
                self.cfg.background,
                self.cfg.seed,
                limit,
            )

    def train_dataloader(self, trainer: L.Trainer, pl_module: L.LightningModule) -> DataLoader:
        """Pairs of the round the current epoch belongs to, rolled out (or read back) on first use."""
        round_ = trainer.current_epoch // self.cfg.refresh_every_n_epochs
        if round_ != self.round:
            restored = self._restored.get("policy") if self._restored.get("round") == round_ else None
            policy = restored or policy_fingerprint(pl_module.model)
            self.records = self.refresh(trainer, pl_module, round_, policy)
            self.round, self.policy = round_, policy
        dataset = PairDataset(
            self.records, {s.id: s.inputs for s in self.scenes}, anchors=self.cfg.anchor_ties
        )
        # a dev run's few scenes may all tie: it still trains on them as KL anchors (when enabled)
        if dataset.num_pairs == 0 and not (trainer.fast_dev_run and len(dataset)):
            notes = sorted({r.note for r in self.records})
            raise RuntimeError(
                f"round {round_} gave no preference pair from {len(self.records)} scenes ({notes}); raise "
                "stage.rollout.min_std_decades or num_candidates, or lower min_gap"
            )
        return DataLoader(
            dataset,
            batch_size=self.cfg.batch_size,
            shuffle=True,
            collate_fn=collate_pairs,
            num_workers=self.cfg.num_workers,
            drop_last=False,
        )

    def cache(self, trainer: L.Trainer) -> PairCache:
        root = Path(self.cfg.cache_dir)
        return PairCache(root if root.is_absolute() else Path(trainer.default_root_dir) / root)

    def refresh(
        self, trainer: L.Trainer, pl_module: L.LightningModule, round_: int, policy: str
    ) -> list[SceneRecord]:
        """Roll out this rank's scenes of ``round_`` (skipping cached ones) and gather every rank's."""
        rank, world = trainer.global_rank, trainer.world_size
        cache, settings = self.cache(trainer), self.settings
        model = pl_module.model
        mine = [s for s in self.scenes if s.index % world == rank]
        cache.clean_temporaries(round_, [s.id for s in mine])
        local, simulated, start = [], 0, time.perf_counter()
        for scene in mine:
            record = cache.read(round_, scene.id, settings, policy)
            if record is None:
                record = rollout_scene(model, scene, self.cfg, round_, settings, policy, trainer.global_step)
                cache.write(record)
                simulated += 1
            local.append(record)
        records = gather_records(local)
        self._check_failures(records, round_, cache)
        self._log(trainer, records, round_, simulated, time.perf_counter() - start)
        return records

    def _check_failures(self, records: list[SceneRecord], round_: int, cache: PairCache) -> None:
        cands = [c for r in records for c in r.candidates]
        failed = [c for c in cands if c.distance is None]
        if cands and len(failed) > self.cfg.max_failed_fraction * len(cands):
            examples = "; ".join(sorted({c.error or "" for c in failed})[:3])
            raise RuntimeError(
                f"{len(failed)} of {len(cands)} rollouts failed in round {round_} (cache {cache.root}): "
                f"{examples}"
            )

    def _log(
        self, trainer: L.Trainer, records: list[SceneRecord], round_: int, simulated: int, seconds: float
    ) -> None:
        stats = {
            **round_stats(records),
            "rollout/round": float(round_),
            "rollout/simulated_scenes": float(simulated),
            "rollout/seconds": seconds,
        }
        if trainer.is_global_zero:
            for logger in trainer.loggers:
                logger.log_metrics(stats, step=trainer.global_step)
            self.cache(trainer).write_summary(round_, stats)
