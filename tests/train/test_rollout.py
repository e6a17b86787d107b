"""Rollout callback bookkeeping: resumable cache, DDP shares, pair selection, the DPO entry point.

Where a test is about bookkeeping, ``evaluate_physics`` (simulate + render + score) is replaced by a
cheap deterministic stand-in: distance = |sampled log10 E - a per-scene target|. No physics
result is claimed from it. ``test_evaluate_physics_wiring`` checks the real render + score path
with a stand-in for the simulator only (a static object), and the slow test runs the real MPM.
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import physgm.train.rollout as rollout
import physgm.train.rollout_env as env
from physgm.data.synth import SynthConfig, asset_id, generate
from physgm.data.video import VideoConfig, place_object, render_frames, video_camera, write_mp4
from physgm.data.writer import camera_entry, write_json
from physgm.gaussians import Gaussians, read_ply
from physgm.model.physgm import PhysGM
from physgm.physics.materials import PhysicsSpec
from physgm.train.pairs import PairCache
from physgm.train.pretrain import LitPretrain
from physgm.train.rollout_budget import BoundedRun
from tests.model_configs import tiny_config

CONF = Path(__file__).resolve().parents[2] / "conf"
COUNT = 4


@dataclass
class StillTrajectory:
    """A trajectory whose Gaussians never move (what rendering reads of one)."""

    gaussians: Gaussians
    n: int
    plan: object = None
    rest_frame: int | None = None

    def __len__(self) -> int:
        return self.n

    def gaussians_at(self, t: int) -> Gaussians:
        return self.gaussians

    def reordered(self, index: torch.Tensor) -> StillTrajectory:
        return StillTrajectory(self.gaussians[index], self.n, self.plan, self.rest_frame)


def falling_square(frames: int = 10, size: int = 32) -> np.ndarray:
    rng = np.random.default_rng(0)
    tex = rng.integers(0, 180, (3, 3, 3)).repeat(3, 0).repeat(3, 1).astype(np.uint8)
    out = np.full((frames, size, size, 3), 255, np.uint8)
    for t in range(frames):
        y = min(2 + t * t // 2, 20)
        out[t, y : y + 9, 10:19] = tex
    return out


@pytest.fixture(scope="module")
def dpo_root(tmp_path_factory) -> Path:
    """4 tiny synthetic assets, each with a reference video (a falling square), listed in the dpo split."""
    root = tmp_path_factory.mktemp("dpo") / "data"
    summary = generate(
        SynthConfig(count=COUNT, seed=5, resolution=32, gaussians=300, video_fraction=0.0),
        root,
        workers=1,
        progress=False,
    )
    assert summary["done"] == COUNT
    vcfg = VideoConfig()
    for i in range(COUNT):
        vdir = root / asset_id(i) / "videos"
        vdir.mkdir()
        frames = falling_square()
        write_mp4(vdir / "drop.mp4", frames, vcfg.fps)
        cam = video_camera(vcfg, -45.0, 32)
        write_json(
            vdir / "drop.json",
            {
                "scene": "drop",
                "fps": vcfg.fps,
                "frames": len(frames),
                "height_from": "surface",
                "settings": asdict(vcfg),
                "camera": camera_entry(cam.c2w[0], cam.Ks[0], 32, 32),
            },
        )
    (root / "splits" / "dpo.txt").write_text("".join(f"{asset_id(i)}\n" for i in range(COUNT)))
    return root


@pytest.fixture(scope="module")
def stage1_ckpt(tmp_path_factory) -> str:
    torch.manual_seed(0)
    lit = LitPretrain(model=tiny_config().to_dict())
    path = tmp_path_factory.mktemp("ckpt") / "stage1.ckpt"
    import lightning as L

    torch.save(
        {
            "state_dict": lit.state_dict(),
            "hyper_parameters": dict(lit.hparams),
            "pytorch-lightning_version": L.__version__,
        },
        path,
    )
    return str(path)


class Killed(BaseException):
    """Stands for the process being killed (not an Exception, so nothing on the way catches it)."""


class StandIn:
    """Deterministic stand-in for simulate + render + score; records every call."""

    def __init__(self, kill_at_scene: str | None = None):
        self.calls: list[tuple[str, PhysicsSpec]] = []
        self.kill_at_scene = kill_at_scene

    def __call__(self, scene, gaussians, physics, reference, settings, device="cpu"):
        assert reference.dtype == np.uint8 and reference.shape[1:] == (
            32,
            32,
            3,
        )  # the decoded reference video
        assert len(gaussians) > 0 and physics.material and physics.E > 0
        if scene.id == self.kill_at_scene:
            raise Killed()
        self.calls.append((scene.id, physics))
        target = 4.0 + scene.index  # an arbitrary, scene-dependent "true" stiffness
        return env.ClipResult(abs(math.log10(physics.E) - target), mode="stand-in")


def make_callback(root: Path, **over) -> rollout.RolloutCallback:
    cfg = dict(
        data_root=str(root),
        num_views=2,
        num_candidates=3,
        workers=1,
        batch_size=2,
        cache_dir="pairs",
        sim={"resolution": 32, "n_frames": 8},
    )
    return rollout.RolloutCallback(**{**cfg, **over})


def fake_trainer(tmp_path: Path, rank: int = 0, world: int = 1, epoch: int = 0) -> SimpleNamespace:
    return SimpleNamespace(
        global_rank=rank,
        world_size=world,
        default_root_dir=str(tmp_path),
        global_step=0,
        current_epoch=epoch,
        is_global_zero=rank == 0,
        loggers=[],
    )


@pytest.fixture(scope="module")
def policy() -> SimpleNamespace:
    torch.manual_seed(0)
    return SimpleNamespace(model=PhysGM(tiny_config()))


def test_cache_resumes_after_a_kill_and_never_reads_half_files(dpo_root, policy, tmp_path, monkeypatch):
    cb = make_callback(dpo_root)
    cb.setup(None, None, "fit")
    assert [s.id for s in cb.scenes] == [asset_id(i) for i in range(COUNT)]
    killer = StandIn(kill_at_scene=asset_id(2))
    monkeypatch.setattr(rollout, "evaluate_physics", killer)
    trainer = fake_trainer(tmp_path)
    with pytest.raises(Killed):
        cb.refresh(trainer, policy, 0, "p0")
    assert {s for s, _ in killer.calls} == {asset_id(0), asset_id(1)}
    cache = PairCache(tmp_path / "pairs")
    first = cache.read(0, asset_id(0), cb.settings, "p0")
    assert first is not None and cache.read(0, asset_id(2), cb.settings, "p0") is None
    # A truncated file under a final name (and a stale temporary) must be redone, not trusted.
    cache.path(0, asset_id(1)).write_text(cache.path(0, asset_id(1)).read_text()[:40])
    cache.path(0, asset_id(3)).with_name(f".{asset_id(3)}.json.tmp-999").write_text("{")

    rerun = StandIn()
    monkeypatch.setattr(rollout, "evaluate_physics", rerun)
    with pytest.warns(UserWarning, match="unreadable"):
        records = cb.refresh(trainer, policy, 0, "p0")
    assert sorted({s for s, _ in rerun.calls}) == [asset_id(1), asset_id(2), asset_id(3)]
    assert len(rerun.calls) == 3 * 3
    assert [r.scene for r in records] == [asset_id(i) for i in range(COUNT)]
    assert records[0] == first  # read back, not resimulated
    assert not list((tmp_path / "pairs" / "round_0000").glob(".*"))
    # Same scene and round: the same candidates whatever the interruption (seeded per scene and round).
    redo = [p for s, p in rerun.calls if s == asset_id(1)]
    assert [c.log10_E for c in records[1].candidates] == pytest.approx(
        [math.log10(p.E) for p in redo], abs=1e-5
    )
    # A third run simulates nothing.
    again = StandIn()
    monkeypatch.setattr(rollout, "evaluate_physics", again)
    assert cb.refresh(trainer, policy, 0, "p0") == records and again.calls == []
    # A new round samples again, and so does the same round drawn from other policy weights.
    cb.refresh(trainer, policy, 1, "p0")
    assert len(again.calls) == COUNT * 3
    cb.refresh(trainer, policy, 0, "p1")
    assert len(again.calls) == 2 * COUNT * 3


def test_winner_is_lowest_distance_and_candidates_are_raw_samples(
    dpo_root, policy, tmp_path, monkeypatch, capsys
):
    monkeypatch.setattr(rollout, "evaluate_physics", StandIn())
    cb = make_callback(dpo_root, workers=2, num_candidates=4, min_std_decades=1.0)
    cb.setup(None, None, "fit")
    records = cb.refresh(fake_trainer(tmp_path), policy, 0, "p0")
    progress = capsys.readouterr().err.splitlines()
    assert [line.split(" scenes")[0] for line in progress if line.startswith("rollout round")] == [
        f"rollout round 0: {i}/{COUNT}" for i in range(1, COUNT + 1)
    ]
    assert f"{COUNT} pairs written, 0 candidates skipped" in progress[-1]
    for r in records:
        d = [c.distance for c in r.candidates]
        assert len(d) == 4 and r.has_pair
        assert r.winner == int(np.argmin(d)) and r.loser == int(np.argmax(d))
        target = 4.0 + r.scene_index
        assert d == pytest.approx(
            [abs(min(max(c.log10_E, 3.0), 11.7) - target) for c in r.candidates], abs=1e-4
        )
    # The exploration floor of 1 decade shows in the spread of the draws.
    spread = np.std([c.log10_E for r in records for c in r.candidates])
    assert spread > 0.5


def test_anchor_pairing_rereads_cached_candidates_and_needs_a_policy_draw(
    dpo_root, policy, tmp_path, monkeypatch
):
    monkeypatch.setattr(rollout, "evaluate_physics", StandIn())
    trainer = fake_trainer(tmp_path)
    first = make_callback(dpo_root, proposal="wide", wide_fraction=2 / 3)
    first.setup(None, None, "fit")
    extremes = first.refresh(trainer, policy, 0, "p0")
    anchored = make_callback(dpo_root, proposal="wide", wide_fraction=2 / 3, pairing="anchor")
    anchored.setup(None, None, "fit")
    assert anchored.settings == first.settings  # the pairing is not part of the cache key
    again = StandIn()
    monkeypatch.setattr(rollout, "evaluate_physics", again)
    records = anchored.refresh(trainer, policy, 0, "p0")
    assert again.calls == []  # the same candidates, paired again
    for old, new in zip(extremes, records, strict=True):
        assert new.candidates == old.candidates
        assert [c.source for c in new.candidates] == ["wide", "wide", "policy"]
        d = [c.distance for c in new.candidates]
        assert old.loser == int(np.argmax(d))
        if int(np.argmin(d)) == 2:
            assert not new.has_pair and new.note == "the policy's draw won"
        else:
            assert (new.winner, new.loser) == (int(np.argmin(d)), 2)
    assert any(r.has_pair for r in records)
    with pytest.raises(ValueError, match="pairing=anchor needs a candidate drawn from the policy"):
        make_callback(dpo_root, proposal="wide", wide_fraction=1.0, pairing="anchor")
    with pytest.raises(ValueError, match="rollout.pairing must be one of"):
        make_callback(dpo_root, pairing="worst")


def test_mode_material_candidates_share_the_most_likely_material(dpo_root, policy, tmp_path, monkeypatch):
    monkeypatch.setattr(rollout, "evaluate_physics", StandIn())
    cb = make_callback(dpo_root, material="mode", num_candidates=4)
    cb.setup(None, None, "fit")
    for r, scene in zip(cb.refresh(fake_trainer(tmp_path), policy, 0, "p0"), cb.scenes, strict=True):
        _, posterior = env.predict(policy.model, scene.inputs)
        assert {c.material for c in r.candidates} == {int(posterior.material_logits.argmax())}
        assert len({c.log10_E for c in r.candidates}) == 4


def test_ddp_ranks_simulate_disjoint_shares(dpo_root, policy, tmp_path, monkeypatch):
    seen = {}
    for rank in (0, 1):
        stand_in = StandIn()
        monkeypatch.setattr(rollout, "evaluate_physics", stand_in)
        cb = make_callback(dpo_root)
        cb.setup(None, None, "fit")
        local = cb.refresh(fake_trainer(tmp_path, rank=rank, world=2), policy, 0, "p0")
        seen[rank] = {s for s, _ in stand_in.calls}
        assert [r.scene_index % 2 for r in local] == [rank] * (
            COUNT // 2
        )  # single process: no gather partner
    assert seen[0] == {asset_id(0), asset_id(2)} and seen[1] == {asset_id(1), asset_id(3)}


def test_evaluate_physics_wiring(dpo_root, monkeypatch):
    """Placement, camera, frame rate and scene given to the simulator; real render + score, still object."""
    scene = env.load_scenes(dpo_root, "dpo", num_views=1)[0]
    n = 200
    gen = torch.Generator().manual_seed(0)
    g = Gaussians(
        torch.rand(n, 3, generator=gen) * 0.6 - 0.3,
        torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        torch.full((n, 3), 0.03),
        torch.full((n,), 0.9),
        torch.rand(n, 3, generator=gen) * 0.7,
    )
    placed, _ = place_object(g, scene.video)
    seen = {}

    def static_simulate(
        gaussians,
        physics,
        scene_name,
        cameras,
        n_frames,
        planner,
        solver,
        scene_overrides,
        device,
        budget,
        start,
    ):
        seen.update(
            g=gaussians,
            scene=scene_name,
            cams=cameras,
            n=n_frames,
            solver=solver,
            over=scene_overrides,
            physics=physics,
            planner=planner,
            budget=budget,
        )
        return BoundedRun(
            StillTrajectory(gaussians, n_frames, plan=SimpleNamespace(mode="rigid", E_used=1.0)),
            planner,
            -1,
            0.0,
            0.0,
        )

    monkeypatch.setattr(env, "bounded_simulate", static_simulate)
    settings = env.SimSettings(resolution=32, n_frames=6, backend="warp")
    camera = env.render_camera(scene, 32)
    reference = render_frames(StillTrajectory(placed, 6), camera, "warp", 1.0)
    result = env.evaluate_physics(scene, g, PhysicsSpec("rubber", E=1e6, nu=0.45), reference, settings)
    torch.testing.assert_close(seen["g"].means, placed.means)
    assert seen["g"].means[:, 2].min().item() == pytest.approx(scene.video.drop_height_m, abs=1e-6)
    assert (
        seen["scene"] == "drop" and seen["n"] == 6 and seen["over"] == {"height": scene.video.drop_height_m}
    )
    assert seen["solver"].frame_dt == pytest.approx(1 / scene.fps)
    # Every Gaussian carries mass (min(0.05, half the faintest opacity 0.9)), and explicit MPM for every
    # candidate, as for the reference videos: no pressure split where the candidate's E would pick it.
    assert seen["planner"] == {"min_opacity": pytest.approx(0.05), "allow_pressure": False}
    # Rendering at half the reference size: the pixel bounds halve, so the plan is the reference's.
    from physgm.sim.planner import PlannerConfig

    half = env.SimSettings(resolution=16, n_frames=6, backend="warp", planner={"cells_across": 7})
    env.evaluate_physics(scene, g, PhysicsSpec("rubber", E=1e6, nu=0.45), reference, half)
    assert seen["cams"].width == 16 and seen["cams"].Ks[0, 0, 0].item() == pytest.approx(
        scene.camera.Ks[0, 0, 0].item() / 2
    )
    d = PlannerConfig()
    assert seen["planner"] == {
        "min_opacity": pytest.approx(0.05),
        "allow_pressure": False,
        "bound_px": pytest.approx(d.bound_px / 2),
        "rest_px": pytest.approx(d.rest_px / 2),
        "rest_budget_px": pytest.approx(d.rest_budget_px / 2),
        "cells_across": 7,
    }
    torch.testing.assert_close(seen["cams"].c2w, scene.camera.c2w)
    assert seen["budget"].max_seconds == 30.0  # the default budget reaches the simulator
    # A still object scored against itself (through the codec): tracks agree exactly, the silhouette
    # terms only see the codec's edge pixels at 32 px.
    terms = result.terms
    assert terms["tracks"] == pytest.approx(0.0, abs=1e-6) and result.mode == "rigid"
    assert result.distance == pytest.approx(terms["tracks"] + terms["profile"] + 0.5 * terms["silhouette"])
    assert terms["profile"] < 0.1 and terms["silhouette"] < 0.2


def compose_dpo(dpo_root, stage1_ckpt, tmp_path, *overrides: str):
    """``python train.py stage=dpo`` from the stage-1 file on the test scenes, writing under tmp_path."""
    from hydra import compose, initialize_config_dir

    base = [
        "stage=dpo",
        f"stage.init_ckpt={stage1_ckpt}",
        f"++data.root={dpo_root}",
        f"paths.output_dir={tmp_path}",
    ]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("train", overrides=[*base, *overrides])


def test_fit_trains_and_resumes_mid_round_from_the_cache(dpo_root, stage1_ckpt, tmp_path, monkeypatch):
    from physgm.train.run import run

    torch.set_num_threads(1)
    stand_in = StandIn()
    monkeypatch.setattr(rollout, "evaluate_physics", stand_in)
    overrides = [
        "experiment=tiny_cpu_dpo",
        "++data.input_resolution=32",
        "stage.rollout.refresh_every_n_epochs=2",
        "stage.rollout.batch_size=2",
        "stage.rollout.num_views=2",
        "stage.rollout.workers=1",
        "stage.rollout.sim.resolution=32",
        "callbacks.progress_bar=null",
        "stage.optim.warmup_steps=1",
    ]

    def train(*extra: str) -> dict:
        return run(compose_dpo(dpo_root, stage1_ckpt, tmp_path, *overrides, *extra))

    metrics = train("stage.trainer.max_epochs=1")
    assert len(stand_in.calls) == COUNT * 3  # round 0: every scene, K = 3
    for key in ("train/loss_epoch", "rewards/margins_epoch", "rewards/accuracies_epoch", "train/kl_epoch"):
        assert key in metrics and math.isfinite(metrics[key]), key
    summary = json.loads((tmp_path / "pairs" / "round_0000" / "_summary.json").read_text())
    assert summary["rollout/scenes"] == COUNT and summary["rollout/pairs"] >= 1
    ckpt = torch.load(tmp_path / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert all(k.startswith("model.") for k in ckpt["state_dict"])

    # A real crash in epoch 1 of a fresh run: last.ckpt must be the end of epoch 0 (Lightning saves
    # nothing at an epoch end unless told to, the trainer config having check_val_every_n_epoch null).
    from physgm.train.dpo import LitDPO

    (tmp_path / "checkpoints" / "last.ckpt").unlink()
    step = LitDPO.training_step

    def crash_in_epoch_1(self, *args, **kwargs):
        if self.current_epoch == 1:
            raise RuntimeError("simulated crash")
        return step(self, *args, **kwargs)

    monkeypatch.setattr(LitDPO, "training_step", crash_in_epoch_1)
    with pytest.raises(RuntimeError, match="simulated crash"):
        train("stage.trainer.max_epochs=3")
    monkeypatch.setattr(LitDPO, "training_step", step)
    assert (
        torch.load(tmp_path / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)["epoch"]
        == 0
    )
    # Resume: epoch 1 is still round 0 (read from the cache), epoch 2 starts round 1.
    again = StandIn()
    monkeypatch.setattr(rollout, "evaluate_physics", again)
    train("stage.trainer.max_epochs=3", "ckpt_path=last")
    assert len(again.calls) == COUNT * 3
    assert (tmp_path / "pairs" / "round_0001" / "_summary.json").is_file()


def test_fit_stops_on_a_part_outside_the_physics_head_before_any_rollout(
    dpo_root, stage1_ckpt, tmp_path, monkeypatch
):
    from physgm.errors import UserError
    from physgm.train.run import run

    stand_in = StandIn()
    monkeypatch.setattr(rollout, "evaluate_physics", stand_in)
    with pytest.raises(UserError, match="starts with physics_head"):
        run(compose_dpo(dpo_root, stage1_ckpt, tmp_path, "stage.trainable=backbone"))
    assert not stand_in.calls


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("stage.rollout.workers=two", "rollout setting workers='two' must be a number"),
        ("stage.loss.factorised=yes", "loss setting factorised='yes' must be true or false"),
        ("stage.optim.warmup_steps=2.5", "optim setting warmup_steps=2.5 must be an integer"),
    ],
)
def test_fit_stops_on_a_setting_of_the_wrong_type_before_the_data(
    override, message, dpo_root, stage1_ckpt, tmp_path, monkeypatch
):
    # Checked before ensure_data, which a run without a data set spends minutes generating.
    from physgm.errors import UserError
    from physgm.train import run as run_module

    def no_data(*args, **kwargs):
        raise AssertionError("the data set was looked for before the settings were checked")

    monkeypatch.setattr(run_module, "ensure_data", no_data)
    with pytest.raises(UserError, match=f"bad stage settings: {message}"):
        run_module.run(compose_dpo(dpo_root, stage1_ckpt, tmp_path, override))


@pytest.mark.parametrize("experiment", [None, "tiny_cpu_dpo"])
def test_fast_dev_run_trains_one_batch_and_rolls_out_only_its_scenes(
    experiment, dpo_root, stage1_ckpt, tmp_path, monkeypatch
):
    """stage.optim.warmup_steps=5 against fast_dev_run's 1 step used to stop the run; and a dev run
    rolled out every scene of the split (hours on the default data) before its one batch."""
    from physgm.train.run import run

    stand_in = StandIn()
    monkeypatch.setattr(rollout, "evaluate_physics", stand_in)
    overrides = [
        *([f"experiment={experiment}"] if experiment else []),
        "++data.input_resolution=32",
        "stage.rollout.batch_size=2",
        "stage.rollout.num_views=2",
        "stage.rollout.workers=1",
        "callbacks.progress_bar=null",
        "+trainer.fast_dev_run=true",
    ]
    cfg = compose_dpo(dpo_root, stage1_ckpt, tmp_path, *overrides)
    assert cfg.stage.optim.warmup_steps == 5
    metrics = run(cfg)
    assert len(stand_in.calls) == 2 * 3  # one batch of 2 scenes (of 4) x K = 3 candidates
    assert math.isfinite(metrics["train/loss_epoch"])


@pytest.mark.slow
def test_real_rollout_on_a_generated_drop_scene(tmp_path):
    """One scene generated with a real reference video; K = 2 real MPM rollouts (slow: minutes on CPU)."""
    root = tmp_path / "data"
    summary = generate(
        SynthConfig(count=1, seed=11, resolution=32, gaussians=400, video_fraction=1.0, materials=["jelly"]),
        root,
        workers=1,
        progress=False,
    )
    assert summary["done"] == 1, summary["failures"]
    (root / "splits" / "dpo.txt").write_text(f"{asset_id(0)}\n")
    torch.manual_seed(0)
    model = PhysGM(tiny_config())
    cb = make_callback(
        root, num_candidates=2, sim={"resolution": 32, "n_frames": 12, "planner": {"cells_across": 10}}
    )
    cb.setup(None, None, "fit")
    (record,) = cb.refresh(fake_trainer(tmp_path), SimpleNamespace(model=model), 0, "p0")
    assert all(c.distance is not None and math.isfinite(c.distance) for c in record.candidates), record


def _stage2_ckpt(stage1_ckpt: str, path: Path, shift: float) -> str:
    """A DPO checkpoint: stage 1 with the mean of normalised log10 E shifted by ``shift``."""
    import lightning as L

    from physgm.train.dpo import LitDPO

    lit = LitDPO(init_ckpt=stage1_ckpt, inputs={"num_views": 2, "input_resolution": 32, "background": 1.0})
    with torch.no_grad():
        lit.model.physics_head.young[-1].bias[0] += shift
    state = {"state_dict": lit.state_dict(), "hyper_parameters": dict(lit.hparams)}
    torch.save({**state, "pytorch-lightning_version": L.__version__}, path)
    return str(path)


def test_evaluate_command_compares_two_checkpoints(dpo_root, stage1_ckpt, tmp_path, monkeypatch, capsys):
    """Bookkeeping of ``python -m physgm.train.evaluate_dpo``, stand-in score |mean log10 E - true|."""
    from physgm.train import evaluate_dpo

    # The mean of normalised log10 E shifted by +0.5 (2.2 decades).
    dpo_path = _stage2_ckpt(stage1_ckpt, tmp_path / "dpo.ckpt", 0.5)
    truth = {s.id: s.log10_E for s in env.load_scenes(dpo_root, "dpo", num_views=2, input_resolution=32)}

    def score(scene, gaussians, physics, reference, settings, device="cpu", keep_frames=False):
        # The rollout score is the stand-in; the clip is the reference itself, so the command's own
        # trajectory and perceptual distances must come out 0.
        return env.ClipResult(abs(math.log10(physics.E) - truth[scene.id]), mode="stand-in", frames=reference)

    monkeypatch.setattr(env, "evaluate_physics", score)
    out = tmp_path / "eval"
    argv = ["--pretrain", stage1_ckpt, "--dpo", str(dpo_path), "--data", str(dpo_root), "--split", "dpo"]
    assert evaluate_dpo.main([*argv, "--frames", "6", "--out", str(out), "--workers", "1"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report == json.loads((out / "evaluate_dpo.json").read_text())
    assert report["scenes"] == COUNT and report["views"] == 2 and report["input_resolution"] == 32
    rows = report["per_scene"]
    for r in rows:
        for name in ("pretrain", "dpo"):
            assert r[name]["score"] == pytest.approx(
                abs(min(max(r[name]["log10_E"], 3.0), 11.7) - r["log10_E"]), abs=1e-4
            )
            assert r[name]["distance"] == pytest.approx(0.0, abs=1e-6)
            assert r[name]["perceptual"] == pytest.approx(0.0, abs=1e-6)
            assert r[name]["abs_log10_E_error"] == pytest.approx(abs(r[name]["log10_E"] - r["log10_E"]))
        assert r["dpo"]["log10_E"] - r["pretrain"]["log10_E"] == pytest.approx(0.5 * 8.7 / 2, abs=1e-3)
    overall = report["summary"]["overall"]
    for name in ("pretrain", "dpo"):
        assert overall[name]["mean_score"] == pytest.approx(np.mean([r[name]["score"] for r in rows]))
        assert overall[name]["median_abs_log10_E_error"] == pytest.approx(
            np.median([r[name]["abs_log10_E_error"] for r in rows])
        )
    gain = 1 - overall["dpo"]["median_abs_log10_E_error"] / overall["pretrain"]["median_abs_log10_E_error"]
    assert overall["gain"]["median_abs_log10_E_error"] == pytest.approx(gain)
    summary = report["summary"]
    assert set(evaluate_dpo.KEY_MATERIALS) <= set(summary) and "rubber" in summary
    assert summary["metal"]["pretrain"]["n"] == sum(r["material"] == "metal" for r in rows)
    # One contact sheet per material present: reference, stage 1 and stage 2 rows.
    present = {r["material"] for r in rows}
    assert set(report["sheets"]) == present and all(Path(p).is_file() for p in report["sheets"].values())
    text = (out / "evaluate_dpo.md").read_text()
    assert text.count("\n") == len(summary) + 2 and "| overall |" in text and "| rubber |" in text
    assert "stage 1 perceptual" in text and "stage 2 traj dist" in text


def test_evaluate_command_reads_stored_rollouts_and_shares_stage_1(
    dpo_root, stage1_ckpt, tmp_path, monkeypatch, capsys
):
    """A second evaluation simulates nothing it has stored; another stage-2 model sharing the
    folder simulates only itself; other settings simulate everything again."""
    from physgm.train import evaluate_dpo

    calls = []

    def score(scene, gaussians, physics, reference, settings, device="cpu", keep_frames=False):
        calls.append(math.log10(physics.E))
        return env.ClipResult(abs(math.log10(physics.E) - 6.0), mode="stand-in", frames=reference)

    monkeypatch.setattr(env, "evaluate_physics", score)
    shared = tmp_path / "rollouts"

    def evaluate(dpo: str, out: str, frames: str = "6") -> dict:
        argv = ["--pretrain", stage1_ckpt, "--dpo", dpo, "--data", str(dpo_root), "--split", "dpo"]
        argv += [
            "--frames",
            frames,
            "--out",
            str(tmp_path / out),
            "--rollouts",
            str(shared),
            "--workers",
            "1",
        ]
        calls.clear()
        assert evaluate_dpo.main(argv) == 0
        return json.loads(capsys.readouterr().out)

    a, b = (
        _stage2_ckpt(stage1_ckpt, tmp_path / f"{n}.ckpt", shift) for n, shift in (("a", 0.5), ("b", -0.5))
    )
    first = evaluate(a, "a")
    assert len(calls) == 2 * COUNT
    again = evaluate(a, "a2")
    assert calls == [] and again["per_scene"] == first["per_scene"]
    other = evaluate(b, "b")
    assert len(calls) == COUNT  # stage 2 only
    assert [r["pretrain"] for r in other["per_scene"]] == [r["pretrain"] for r in first["per_scene"]]
    assert [r["dpo"]["log10_E"] for r in other["per_scene"]] != [
        r["dpo"]["log10_E"] for r in first["per_scene"]
    ]
    evaluate(a, "a3", frames="5")
    assert len(calls) == 2 * COUNT
    assert not list(shared.glob("*.tmp*"))


def test_asset_gaussians_are_what_candidates_simulate(dpo_root, policy, tmp_path, monkeypatch):
    seen: dict[str, int] = {}

    def record(scene, gaussians, physics, reference, settings, device="cpu"):
        seen[scene.id] = len(gaussians)
        return env.ClipResult(abs(math.log10(physics.E) - 5.0), mode="stand-in")

    monkeypatch.setattr(rollout, "evaluate_physics", record)
    predicted = make_callback(dpo_root)
    predicted.setup(None, None, "fit")
    predicted.refresh(fake_trainer(tmp_path / "a"), policy, 0, "p0")
    from_model = dict(seen)
    asset = make_callback(dpo_root, gaussians="asset")
    asset.setup(None, None, "fit")
    assert asset.settings != predicted.settings  # the pair cache tells the two apart
    asset.refresh(fake_trainer(tmp_path / "b"), policy, 0, "p0")
    for aid in from_model:
        assert seen[aid] == len(read_ply(dpo_root / aid / "gaussians.ply")) != from_model[aid]


def test_asset_gaussians_need_a_gaussians_file_per_scene(dpo_root, tmp_path):
    with pytest.raises(ValueError, match="rollout.gaussians must be one of"):
        make_callback(dpo_root, gaussians="mesh")
    root = tmp_path / "data"
    shutil.copytree(dpo_root, root)
    (root / asset_id(1) / "gaussians.ply").unlink()
    cb = make_callback(root, gaussians="asset")
    with pytest.raises(ValueError, match=f"1 scenes .* have none \\({asset_id(1)}\\)"):
        cb.setup(None, None, "fit")


def test_reference_videos_placed_the_old_way_are_named(dpo_root, tmp_path):
    # Videos simulated before drop heights were taken from the object's surface start half a
    # particle spacing lower than today's rollouts: loading them says so and how to fix it.
    root = tmp_path / "data"
    shutil.copytree(dpo_root, root)
    meta_path = root / asset_id(2) / "videos" / "drop.json"
    meta = json.loads(meta_path.read_text())
    del meta["height_from"]
    meta_path.write_text(json.dumps(meta))
    with pytest.warns(UserWarning, match=f"1 reference video.*regenerate.*{asset_id(2)}"):
        scenes = env.load_scenes(root, "dpo", num_views=1)
    assert len(scenes) == COUNT  # still usable
