"""DPO rollouts: propose physics per scene, simulate, render, score against reference videos, pair.

For each scene of the DPO split the policy predicts Gaussians and a physics posterior from the
scene's input views; K candidates come from the configured proposal (``physgm.train.proposal``:
the policy, or a wider one), each is simulated, rendered and scored by the rollout environment
(``physgm.train.rollout_env``) within its time budget. The lowest score wins, the highest loses
(``physgm.train.pairs``).

``RolloutCallback`` does this once per refresh round and hands the DPO stage its dataloader.
Under DDP each rank simulates the scenes with ``index % world_size == rank``; the records are
gathered so every rank holds every pair, and Lightning's distributed sampler splits the pairs.
"""

from __future__ import annotations

import math
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import lightning as L
import torch
from torch.utils.data import DataLoader

from physgm.gaussians import read_ply
from physgm.physics.materials import MATERIAL_NAMES
from physgm.setting_types import check_types
from physgm.train.pairs import (
    PAIRINGS,
    Candidate,
    PairCache,
    PairDataset,
    SceneRecord,
    collate_pairs,
    gather_records,
    policy_fingerprint,
    round_stats,
    select_pair,
    settings_hash,
)
from physgm.train.proposal import PROPOSALS, ProposalSettings, propose, scene_generator, wide_count
from physgm.train.rollout_env import (
    RolloutScene,
    SimSettings,
    evaluate_physics,
    load_scenes,
    physics_spec,
    predict,
    reference_frames,
    warp_device,
)
from physgm.warp_runtime import preload

GAUSSIAN_SOURCES = ("predicted", "asset")


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
    num_candidates: int = 3  # K physics candidates per scene and round
    proposal: str = "policy"  # a key of physgm.train.proposal.PROPOSALS: "policy" (on-policy) or "wide"
    wide_fraction: float = 2 / 3  # "wide": share of K stratified over the material's log10 E range
    material: str = "sample"  # "sample": candidates draw the material too; "mode": all use the most likely
    refresh_every_n_epochs: int = 4  # new rollouts (a new round) every N epochs
    min_std_decades: float = 0.3  # exploration floor: policy draws' log10 E std is at least this
    min_std_nu: float = 0.03  # and nu's std at least this
    min_gap: float = 0.002  # winner and loser closer than this (score units) is a tie: no pair
    pairing: str = "extremes"  # physgm.train.pairs.PAIRINGS: which candidate loses (best vs worst, or vs
    # the policy's own draw); pairs are chosen again from the cached candidates, so it is not in the cache key
    anchor_ties: bool = False  # serve tie scenes too, for the KL anchor (loss.kl_weight)
    max_failed_fraction: float = 0.5  # more failed rollouts than this in a round stops training
    workers: int = 2  # candidates simulated at once (threads; Warp releases the GIL)
    batch_size: int = 8  # pairs per training batch (per device)
    num_workers: int = 0  # DataLoader workers
    cache_dir: str = "pairs"  # the pair cache (one folder per round)
    progress: bool = True  # one line per scene on stderr: scenes done, seconds, pairs written
    # What the candidates are simulated on: "predicted", the policy's own Gaussians (the paper's), or
    # "asset", the scene's gaussians.ply that its reference video was made from (synthetic data sets
    # have them). With the model's blurry Gaussians a stiffer E than the truth often tracks the video
    # best; with the asset's own, the score is lowest at the true E (docs/model.md).
    gaussians: str = "predicted"
    sim: SimSettings = field(default_factory=SimSettings)

    def __post_init__(self) -> None:
        check_types(self, "rollout setting")
        if isinstance(self.sim, dict):
            self.sim = SimSettings(**self.sim)
        if self.material not in ("sample", "mode"):
            raise ValueError(f"rollout.material must be 'sample' or 'mode', got {self.material!r}")
        if self.gaussians not in GAUSSIAN_SOURCES:
            raise ValueError(
                f"rollout.gaussians must be one of {', '.join(GAUSSIAN_SOURCES)}, got {self.gaussians!r}"
            )
        if self.proposal not in PROPOSALS:
            raise ValueError(f"rollout.proposal must be one of {', '.join(PROPOSALS)}, got {self.proposal!r}")
        if not 0.0 <= self.wide_fraction <= 1.0:
            raise ValueError(f"rollout.wide_fraction must be in [0, 1], got {self.wide_fraction}")
        if self.pairing not in PAIRINGS:
            raise ValueError(f"rollout.pairing must be one of {', '.join(PAIRINGS)}, got {self.pairing!r}")
        if (
            self.pairing == "anchor"
            and self.proposal == "wide"
            and wide_count(self.num_candidates, self.wide_fraction) == self.num_candidates
        ):
            raise ValueError(
                "rollout.pairing=anchor needs a candidate drawn from the policy, but wide_fraction "
                f"{self.wide_fraction} makes all {self.num_candidates} candidates wide; lower it"
            )
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

    @property
    def proposal_settings(self) -> ProposalSettings:
        return ProposalSettings(self.material, self.min_std_decades, self.min_std_nu, self.wide_fraction)


def rollout_scene(
    model: torch.nn.Module,
    scene: RolloutScene,
    cfg: RolloutConfig,
    round_: int,
    settings: str,
    policy: str = "",
    global_step: int = 0,
) -> SceneRecord:
    """Propose K candidates for one scene, simulate and score each within the budget, pick the pair."""
    gaussians, posterior = predict(model, scene.inputs)
    if cfg.gaussians == "asset":
        gaussians = read_ply(asset_gaussians_path(cfg, scene), keep_sh=False)
    generator = scene_generator(cfg.seed, round_, scene.id)
    drawn = propose(cfg.proposal, posterior.cpu_float(), cfg.num_candidates, cfg.proposal_settings, generator)
    draws = drawn.sample
    reference = reference_frames(scene, cfg.sim.n_frames)
    device = warp_device(cfg.sim.device, next(model.parameters()).device)

    def run(k: int) -> Candidate:
        cand = Candidate(
            int(draws.material[0, k]),
            MATERIAL_NAMES[int(draws.material[0, k])],
            float(draws.log10_E[0, k]),
            float(draws.nu[0, k]),
            None,
            source=drawn.sources[k],
        )
        start = time.perf_counter()
        try:  # a draw the simulator cannot take (e.g. non-finite) raises ValueError: recorded below
            physics = physics_spec(draws, k)
            result = evaluate_physics(scene, gaussians, physics, reference, cfg.sim, device)
            cand.distance, cand.mode, cand.skipped = result.distance, result.mode, result.skipped
            cand.fallback, cand.predicted_error_px = result.fallback, result.predicted_error_px
            cand.terms = {k: v for k, v in result.terms.items() if math.isfinite(v)}
            if cand.distance is None and not cand.skipped:
                cand.error = "score is not finite (object lost by the tracker)"
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
    winner, loser, note = select_pair(candidates, cfg.min_gap, cfg.pairing)
    return SceneRecord(
        scene.id, scene.index, round_, settings, policy, candidates, winner, loser, global_step, note
    )


def asset_gaussians_path(cfg: RolloutConfig, scene: RolloutScene) -> Path:
    return Path(cfg.data_root) / scene.id / "gaussians.ply"


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
            "progress",
            "pairing",
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
            if self.cfg.gaussians == "asset":
                missing = [s.id for s in self.scenes if not asset_gaussians_path(self.cfg, s).is_file()]
                if missing:
                    raise ValueError(
                        f"rollout.gaussians=asset simulates each scene's gaussians.ply, and {len(missing)} "
                        f"scenes of {self.cfg.data_root} have none ({', '.join(missing[:3])}); use "
                        "rollout.gaussians=predicted for data sets without them"
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
            else:
                record.pair_again(self.cfg.min_gap, self.cfg.pairing)
            local.append(record)
            if self.cfg.progress:
                self._progress(round_, local, len(mine), simulated, time.perf_counter() - start)
        records = gather_records(local)
        self._check_failures(records, round_, cache)
        self._log(trainer, records, round_, simulated, time.perf_counter() - start)
        return records

    @staticmethod
    def _progress(round_: int, done: list[SceneRecord], total: int, simulated: int, seconds: float) -> None:
        skipped = sum(bool(c.skipped) for r in done for c in r.candidates)
        print(
            f"rollout round {round_}: {len(done)}/{total} scenes ({simulated} simulated, "
            f"{len(done) - simulated} from the cache), {seconds:.0f} s, "
            f"{sum(r.has_pair for r in done)} pairs written, {skipped} candidates skipped over budget",
            file=sys.stderr,
            flush=True,
        )

    def _check_failures(self, records: list[SceneRecord], round_: int, cache: PairCache) -> None:
        cands = [c for r in records for c in r.candidates if not c.skipped]
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
