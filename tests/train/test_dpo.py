"""LitDPO: the loss against hand-computed values, the frozen reference, what trains, checkpoints."""

from __future__ import annotations

import copy
import math

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader

from physgm.cameras import orbit_cameras
from physgm.model.checkpoint import load_model
from physgm.model.posterior import PhysicsPosterior, material_E_ranges
from physgm.physics.materials import MATERIAL_NAMES
from physgm.train.dpo import DPOLossConfig, LitDPO, dpo_loss, log10_E_shift, posterior_kl
from physgm.train.pairs import Candidate, PairDataset, SceneInputs, SceneRecord, collate_pairs
from physgm.train.pretrain import LitPretrain
from tests.model_configs import tiny_config


def features_head_config() -> dict:
    """The tiny model on the frozen MobileNetV2, its material read from the pooled pyramid."""
    cfg = tiny_config().to_dict()
    cfg["backbone"]["encoder"] = {
        "kind": "mobilenet_v2",
        "patch_size": 16,
        "embed_dim": 448,
        "freeze": True,
        "img_size": 32,
    }
    cfg["physics_head"]["material_input"] = "features"
    cfg["physics_head"]["feature_hidden"] = 16
    return cfg


def stage1_checkpoint(path, seed: int = 0, model: dict | None = None) -> str:
    """A stage-1 checkpoint as Lightning writes it (state_dict + plain-dict hyper_parameters)."""
    torch.manual_seed(seed)
    lit = LitPretrain(model=model or tiny_config().to_dict())
    torch.save({"state_dict": lit.state_dict(), "hyper_parameters": dict(lit.hparams)}, path)
    return str(path)


def fake_pairs(n: int = 6, v: int = 2, size: int = 32) -> tuple[list[SceneRecord], dict[str, SceneInputs]]:
    gen = torch.Generator().manual_seed(1)
    inputs, records = {}, []
    cams = orbit_cameras([0.0, 90.0][:v], [0.0] * v, 1.8, 34.0, size, size)
    for i in range(n):
        sid = f"s{i}"
        inputs[sid] = SceneInputs(
            torch.rand(v, 3, size, size, generator=gen), torch.ones(v, 1, size, size), cams.c2w, cams.Ks
        )
        w = Candidate(9, "rubber", 6.0 + 0.1 * i, 0.45, 0.05)
        l = Candidate(9 if i % 2 else 13, "x", 7.5 - 0.1 * i, 0.30, 0.4)
        records.append(SceneRecord(sid, i, 0, "h", "p", [w, l], 0, 1))
    return records, inputs


def fit_on_pairs(lit: LitDPO, tmp_path, max_steps: int) -> L.Trainer:
    """``max_steps`` optimiser steps of ``lit`` on the CPU, nothing written but under tmp_path."""
    trainer = L.Trainer(
        max_steps=max_steps,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=tmp_path,
    )
    trainer.fit(lit)
    return trainer


class PairsDPO(LitDPO):
    """LitDPO fed fixed pairs instead of a rollout callback (this file tests the module, not rollouts)."""

    pairs: tuple = ()

    def train_dataloader(self):
        records, inputs = self.pairs
        return DataLoader(PairDataset(records, inputs), batch_size=3, shuffle=False, collate_fn=collate_pairs)


def test_dpo_loss_matches_hand_computation():
    pw, pl = torch.tensor([-1.0, -2.5]), torch.tensor([-3.0, -0.5])
    rw, rl = torch.tensor([-1.5, -2.0]), torch.tensor([-2.0, -1.0])
    terms = dpo_loss(pw, pl, rw, rl, beta=0.5)
    # Pair 0: chosen ratio 0.5, rejected ratio -1.0 -> logit 0.5 * 1.5 = 0.75.
    # Pair 1: chosen ratio -0.5, rejected ratio 0.5 -> logit 0.5 * -1.0 = -0.5.
    expected = [math.log(1 + math.exp(-0.75)), math.log(1 + math.exp(0.5))]
    assert terms.loss.tolist() == pytest.approx(expected, rel=1e-6)
    assert terms.chosen_rewards.tolist() == pytest.approx([0.25, -0.25])
    assert terms.rejected_rewards.tolist() == pytest.approx([-0.5, 0.25])


def test_conservative_dpo_loss_matches_hand_computation_and_stops_at_its_margin():
    pw, pl = torch.tensor([-1.0, -2.5]), torch.tensor([-3.0, -0.5])
    rw, rl = torch.tensor([-1.5, -2.0]), torch.tensor([-2.0, -1.0])
    terms = dpo_loss(pw, pl, rw, rl, beta=0.5, label_smoothing=0.25)
    # Logits 0.75 and -0.5 as above; 0.75 * -log sigmoid(x) + 0.25 * -log sigmoid(-x).
    expected = [
        0.75 * math.log(1 + math.exp(-0.75)) + 0.25 * math.log(1 + math.exp(0.75)),
        0.75 * math.log(1 + math.exp(0.5)) + 0.25 * math.log(1 + math.exp(-0.5)),
    ]
    assert terms.loss.tolist() == pytest.approx(expected, rel=1e-6)
    # Plain DPO keeps falling with the margin; the conservative loss is lowest at log(3) / beta.
    margin = torch.linspace(0.0, 10.0, 10001, dtype=torch.float64)
    zero = torch.zeros_like(margin)
    plain = dpo_loss(margin, zero, zero, zero, beta=0.5).loss
    smooth = dpo_loss(margin, zero, zero, zero, beta=0.5, label_smoothing=0.25).loss
    assert bool((plain[1:] < plain[:-1]).all())
    assert margin[smooth.argmin()].item() == pytest.approx(math.log(3.0) / 0.5, abs=2e-3)
    with pytest.raises(ValueError, match="label_smoothing"):
        DPOLossConfig(label_smoothing=0.5)


def test_analytic_kl_matches_torch_distributions():
    gen = torch.Generator().manual_seed(0)
    p = PhysicsPosterior(*(torch.randn(3, 15, generator=gen), *torch.randn(4, 3, generator=gen)))
    q = PhysicsPosterior(*(torch.randn(3, 15, generator=gen), *torch.randn(4, 3, generator=gen)))
    D = torch.distributions
    expected = (
        D.kl_divergence(D.Categorical(logits=p.material_logits), D.Categorical(logits=q.material_logits))
        + D.kl_divergence(
            D.Normal(p.z_E_mean, (0.5 * p.z_E_logvar).exp()), D.Normal(q.z_E_mean, (0.5 * q.z_E_logvar).exp())
        )
        + D.kl_divergence(
            D.Normal(p.z_nu_mean, (0.5 * p.z_nu_logvar).exp()),
            D.Normal(q.z_nu_mean, (0.5 * q.z_nu_logvar).exp()),
        )
    )
    torch.testing.assert_close(posterior_kl(p, q), expected)
    assert posterior_kl(p, p).abs().max() < 1e-6


def test_the_logged_E_shift_is_in_decades_of_the_simulated_E():
    logits = torch.full((1, len(MATERIAL_NAMES)), -9.0)
    logits[0, MATERIAL_NAMES.index("jelly")] = 9.0  # E range 1e3-1e5 Pa: z = -1 .. 1 is 2 decades

    def post(z_E: float) -> PhysicsPosterior:
        zero = torch.zeros(1)
        return PhysicsPosterior(logits, torch.tensor([z_E]), zero, zero, zero, material_E_ranges())

    # half a unit of z in jelly's frame is half a decade (not half of the global 8.7-decade frame)
    assert log10_E_shift(post(0.5), post(0.0)).item() == pytest.approx(0.5, abs=1e-6)


def test_reference_is_a_frozen_copy_outside_the_module_tree(tmp_path):
    lit = LitDPO(init_ckpt=stage1_checkpoint(tmp_path / "s1.ckpt"))
    ref = lit.reference
    assert ref is not lit.model and not ref.training
    assert all(not p.requires_grad for p in ref.parameters())
    policy_ids = {id(p) for p in lit.model.parameters()}
    assert not policy_ids & {id(p) for p in ref.parameters()}
    assert all(k.startswith("model.") for k in lit.state_dict()) and len(lit.state_dict()) == len(
        lit.model.state_dict()
    )
    assert not any(m is ref for m in lit.modules())
    # Same weights as the stage-1 model it was copied from.
    stage1, _ = load_model(tmp_path / "s1.ckpt")
    for a, b in zip(stage1.state_dict().values(), ref.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    # Only the physics head trains; the rest is frozen and stays in eval mode in training.
    lit.train()
    assert (
        not lit.model.backbone.training
        and not lit.model.gaussian_head.training
        and lit.model.physics_head.training
    )
    trainable = {id(p) for p in lit.model.parameters() if p.requires_grad}
    assert trainable == {id(p) for p in lit.model.physics_head.parameters()}


def experts_config() -> dict:
    """The shipped model's layout: token classifier and semantic prior, a domain gate and a procedural
    expert, at a prior weight and a material temperature other than the defaults."""
    cfg = features_head_config()
    head = cfg["physics_head"]
    head.update(material_input="token", domain_gate=True, procedural_expert=True)
    head.update(semantic_prior_weight=4.0, material_temperature=1.5)
    return cfg


@pytest.mark.parametrize("material_input", ["token", "features", "experts"])
def test_cached_head_inputs_give_the_full_forward_posteriors(tmp_path, material_input):
    model = {"token": None, "features": features_head_config(), "experts": experts_config()}[material_input]
    lit = LitDPO(init_ckpt=stage1_checkpoint(tmp_path / "s1.ckpt", model=model), loss={"beta": 0.5})
    records, inputs = fake_pairs(n=4)
    with torch.no_grad():
        lit.model.physics_head.young[-1].bias += 0.3  # policy != reference
        if material_input == "experts":  # both experts and the gate's mixture count
            lit.model.physics_head.procedural.out.bias.normal_()
            lit.model.physics_head.material[-1].bias.normal_()
            lit.reference.domain_gate.bias.fill_(0.4)
            lit.model.domain_gate.bias.fill_(0.4)
    batch = collate_pairs([PairDataset(records, inputs)[i] for i in (2, 0, 3)])
    policy, reference = lit.posteriors(batch)
    lit.posteriors(collate_pairs([PairDataset(records, inputs)[i] for i in (1, 0)]))  # partly cached
    assert set(lit._head_inputs) == {"s0", "s1", "s2", "s3"}
    assert all((x.pooled is None) == (material_input == "token") for x in lit._head_inputs.values())
    assert all((x.gate is None) == (material_input != "experts") for x in lit._head_inputs.values())
    with torch.no_grad():
        full = lit.model(batch.images, batch.masks, batch.c2w, batch.Ks).physics
        full_ref = lit.reference(batch.images, batch.masks, batch.c2w, batch.Ks).physics
    for name in ("material_logits", "z_E_mean", "z_E_logvar", "z_nu_mean", "z_nu_logvar"):
        torch.testing.assert_close(getattr(policy, name), getattr(full, name))
        torch.testing.assert_close(getattr(reference, name), getattr(full_ref, name))
    assert not torch.equal(policy.z_E_mean, reference.z_E_mean)


def test_prior_weight_override_trains_policy_and_reference_without_the_shipped_prior(tmp_path):
    """A stage-1 file shipped with w = 16 for real photos is trained at w = 0 on procedural scenes."""
    model = features_head_config()
    model["physics_head"]["semantic_prior_weight"] = 16.0
    s1 = stage1_checkpoint(tmp_path / "s1.ckpt", model=model)
    records, inputs = fake_pairs(n=2)
    batch = collate_pairs([PairDataset(records, inputs)[i] for i in range(2)])
    args = (batch.images, batch.masks, batch.c2w, batch.Ks)
    stage1 = load_model(s1)[0]
    with torch.no_grad():
        with_prior = stage1(*args).physics.material_logits
        stage1.config.physics_head.semantic_prior_weight = 0.0
        head_alone = stage1(*args).physics.material_logits
        lit = LitDPO(init_ckpt=s1, prior_weight=0.0)
        policy, reference = lit.model(*args).physics, lit.reference(*args).physics
    assert not torch.allclose(with_prior.log_softmax(-1), head_alone.log_softmax(-1), atol=1e-3)
    torch.testing.assert_close(policy.material_logits.log_softmax(-1), head_alone.log_softmax(-1))
    torch.testing.assert_close(reference.material_logits.log_softmax(-1), head_alone.log_softmax(-1))
    assert lit.hparams.model["physics_head"]["semantic_prior_weight"] == 0.0  # the DPO file rebuilds at w = 0
    assert LitDPO(init_ckpt=s1).model.config.physics_head.semantic_prior_weight == 16.0  # None: the file's
    with pytest.raises(ValueError, match="mobilenet_v2"):  # a ViT has no ImageNet classes for a prior
        LitDPO(init_ckpt=stage1_checkpoint(tmp_path / "vit.ckpt"), prior_weight=2.0)


def test_factorised_log_prob_drops_E_and_nu_when_materials_differ(tmp_path):
    lit = LitDPO(init_ckpt=stage1_checkpoint(tmp_path / "s1.ckpt"), loss={"factorised": True})
    records, inputs = fake_pairs(n=4)  # odd scenes: same material, even: different
    batch = collate_pairs([PairDataset(records, inputs)[i] for i in range(4)])
    policy, _ = lit.posteriors(batch)
    m, e, n = (t[:, 0] for t in policy.log_prob_terms(batch.winner))
    expected = torch.stack([m[0], m[1] + e[1] + n[1], m[2], m[3] + e[3] + n[3]])
    torch.testing.assert_close(lit.log_prob(policy, batch.winner, batch), expected)
    lit.loss_cfg.factorised = False
    torch.testing.assert_close(lit.log_prob(policy, batch.winner, batch), m + e + n)


def test_loss_masks_tie_anchors_and_adds_the_kl(tmp_path):
    lit = LitDPO(init_ckpt=stage1_checkpoint(tmp_path / "s1.ckpt"), loss={"beta": 0.5, "kl_weight": 0.7})
    lit.log_dict = lambda *a, **k: None  # outside a trainer
    records, inputs = fake_pairs(n=3)
    records[2].winner = records[2].loser = None  # scene s2 is a tie: served as an anchor only
    batch = collate_pairs([PairDataset(records, inputs, anchors=True)[i] for i in range(3)])
    assert batch.has_pair.tolist() == [True, True, False]
    with torch.no_grad():
        lit.model.physics_head.young[-1].bias += 0.2
        policy, reference = lit.posteriors(batch)
        loss = lit.training_step(batch, 0)
    lp = [policy.log_prob(s)[:2, 0] for s in (batch.winner, batch.loser)]
    lr = [reference.log_prob(s)[:2, 0] for s in (batch.winner, batch.loser)]
    expected = (
        dpo_loss(lp[0], lp[1], lr[0], lr[1], 0.5).loss.mean() + 0.7 * posterior_kl(policy, reference).mean()
    )
    torch.testing.assert_close(loss, expected)
    assert posterior_kl(policy, reference)[2] > 0


def test_training_moves_only_the_physics_head_and_never_the_reference(tmp_path):
    torch.set_num_threads(1)
    PairsDPO.pairs = fake_pairs()
    lit = PairsDPO(
        init_ckpt=stage1_checkpoint(tmp_path / "s1.ckpt"),
        loss={"beta": 0.5},
        optim={"lr": 3e-3, "warmup_steps": 1},
    )
    ref_before = copy.deepcopy(lit.reference.state_dict())
    policy_before = copy.deepcopy(lit.model.state_dict())
    trainer = fit_on_pairs(lit, tmp_path, max_steps=4)
    opt = trainer.optimizers[0]
    in_opt = {id(p) for g in opt.param_groups for p in g["params"]}
    assert in_opt == {id(p) for p in lit.model.physics_head.parameters()}
    assert not in_opt & {id(p) for p in lit.reference.parameters()}
    for k, v in lit.reference.state_dict().items():
        assert torch.equal(v, ref_before[k]), f"reference weight {k} changed"
    after = lit.model.state_dict()
    head = [k for k in after if k.startswith("physics_head.")]
    assert any(not torch.equal(after[k], policy_before[k]) for k in head), "physics head did not train"
    for k in after:
        if not k.startswith("physics_head."):
            assert torch.equal(after[k], policy_before[k]), f"frozen weight {k} changed"
    m = trainer.callback_metrics
    for key in (
        "train/loss",
        "rewards/chosen",
        "rewards/rejected",
        "rewards/margins",
        "rewards/accuracies",
        "train/kl",
    ):
        assert key in m and torch.isfinite(m[key]), key
    # 4 steps of DPO on consistent pairs: the winners became relatively more likely than the losers.
    assert m["rewards/margins"] > 0 and m["train/kl"] > 0

    # The checkpoint holds the policy only, reloads without Hydra, and load_model reads it.
    path = tmp_path / "dpo.ckpt"
    trainer.save_checkpoint(path)
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    assert set(ckpt["state_dict"]) == {f"model.{k}" for k in lit.model.state_dict()}
    assert isinstance(ckpt["hyper_parameters"]["model"], dict)
    policy, _ = load_model(path)
    for k, v in lit.model.state_dict().items():
        assert torch.equal(policy.state_dict()[k], v)
    back = LitDPO.load_from_checkpoint(path)
    assert torch.equal(back.model.physics_head.young[-1].weight, lit.model.physics_head.young[-1].weight)
    for (
        k,
        v,
    ) in back.reference.state_dict().items():  # rebuilt from the stage-1 file, not from the DPO weights
        assert torch.equal(v, ref_before[k])


def test_a_part_of_the_physics_head_trains_alone(tmp_path):
    torch.set_num_threads(1)
    PairsDPO.pairs = fake_pairs()
    lit = PairsDPO(
        init_ckpt=stage1_checkpoint(tmp_path / "s1.ckpt"),
        optim={"lr": 3e-3, "warmup_steps": 1},
        trainable="physics_head.young.3",
    )
    before = copy.deepcopy(lit.model.state_dict())
    trainer = fit_on_pairs(lit, tmp_path, max_steps=3)
    in_opt = {id(p) for g in trainer.optimizers[0].param_groups for p in g["params"]}
    assert in_opt == {id(p) for p in lit.model.physics_head.young[3].parameters()}
    after = lit.model.state_dict()
    moved = {k for k in after if not torch.equal(after[k], before[k])}
    assert moved == {"physics_head.young.3.weight", "physics_head.young.3.bias"}
    assert trainer.callback_metrics["rewards/margins"] > 0  # E's readout alone still learns the pairs


def test_trainable_names_a_part_of_the_physics_head(tmp_path):
    s1 = stage1_checkpoint(tmp_path / "s1.ckpt")
    with pytest.raises(ValueError, match="starts with physics_head"):
        LitDPO(init_ckpt=s1, trainable="backbone")
    with pytest.raises(ValueError, match=r"physics_head\.\{.*young"):
        LitDPO(init_ckpt=s1, trainable="physics_head.stiffness")


def test_dpo_checkpoint_loads_without_the_stage1_file(tmp_path):
    s1 = stage1_checkpoint(tmp_path / "s1.ckpt")
    lit = LitDPO(init_ckpt=s1)
    ckpt = {
        "state_dict": lit.state_dict(),
        "hyper_parameters": dict(lit.hparams),
        "pytorch-lightning_version": L.__version__,
    }
    torch.save(ckpt, tmp_path / "dpo.ckpt")
    (tmp_path / "s1.ckpt").unlink()
    back = LitDPO.load_from_checkpoint(tmp_path / "dpo.ckpt")
    assert torch.equal(
        back.model.physics_head.material[-1].weight, lit.model.physics_head.material[-1].weight
    )
    with pytest.raises(RuntimeError, match="stage-1 checkpoint"):
        back.reference  # noqa: B018
