"""Stage 2 (``python train.py stage=dpo``): DPO of the physics head against a frozen stage-1 copy.

The policy is the stage-1 PhysGM with its backbone and Gaussian head frozen (no gradients, eval
mode); only the physics head trains. The reference is a ``copy.deepcopy`` of the policy taken
right after loading the stage-1 weights, frozen, kept in a plain list so it is never a submodule:
it is neither in the optimiser nor in the checkpoint (it is rebuilt from ``init_ckpt`` when a
DPO run resumes). Pairs come from ``physgm.train.rollout.RolloutCallback``.

    loss = -log sigmoid(beta * [(log pi(w) - log pi_ref(w)) - (log pi(l) - log pi_ref(l))])

with log pi the exact ``PhysicsPosterior.log_prob`` of the sampled physics (material class plus
Gaussians on normalised log10 E and nu). The KL to the reference is logged in closed form.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
import torch
import torch.nn.functional as F
from torch import Tensor

from physgm import CHECKPOINT_FORMAT_VERSION
from physgm.errors import UserError
from physgm.model.checkpoint import load_model
from physgm.model.config import PhysGMConfig
from physgm.model.physgm import PhysGM
from physgm.model.posterior import PhysicsPosterior
from physgm.setting_types import check_types
from physgm.train.optim import OptimConfig, build_optimizer
from physgm.train.pairs import DPOBatch


@dataclass
class DPOLossConfig:
    beta: float = 0.5  # inverse temperature of the implicit reward; lower lets the policy move further
    sft_weight: float = 0.0  # optional NLL of the winner under the policy (RPO); 0 is plain DPO
    # True: when winner and loser have different materials, only the material term enters the
    # log-ratios (their E and nu lost or won with the material, so they say nothing about E or nu).
    factorised: bool = False
    kl_weight: float = 0.0  # + weight * KL(pi || pi_ref) on every scene of the batch (pairs and tie anchors)
    # The share of pairs assumed mis-ranked (conservative DPO, Mitchell 2023): each pair also counts,
    # with this weight, as preferring the loser. 0 is plain DPO, whose loss keeps falling as the margin
    # grows; above 0 the margin stops at log((1 - s) / s) / beta.
    label_smoothing: float = 0.0

    def __post_init__(self) -> None:
        check_types(self, "loss setting")
        if not self.beta > 0 or self.sft_weight < 0 or self.kl_weight < 0:
            raise ValueError(
                f"DPO needs beta > 0, sft_weight >= 0 and kl_weight >= 0, got {self.beta}, "
                f"{self.sft_weight}, {self.kl_weight}"
            )
        if not 0 <= self.label_smoothing < 0.5:
            raise ValueError(
                f"loss.label_smoothing is the share of mis-ranked pairs, in [0, 0.5), got "
                f"{self.label_smoothing}; 0 is plain DPO"
            )


@dataclass
class DPOTerms:
    loss: Tensor  # [B] per-pair DPO loss
    chosen_rewards: Tensor  # [B] beta * (log pi(w) - log pi_ref(w)), detached
    rejected_rewards: Tensor  # [B] beta * (log pi(l) - log pi_ref(l)), detached


def dpo_loss(
    policy_chosen: Tensor,  # [B] log pi(w)
    policy_rejected: Tensor,  # [B] log pi(l)
    reference_chosen: Tensor,  # [B] log pi_ref(w)
    reference_rejected: Tensor,  # [B] log pi_ref(l)
    beta: float,
    label_smoothing: float = 0.0,
) -> DPOTerms:
    """The DPO loss of Rafailov et al. (2023) per pair, and the implicit rewards.

    With ``label_smoothing`` s > 0 it is the conservative form: the pair counts as won by the
    winner with weight 1 - s and by the loser with weight s.
    """
    chosen = policy_chosen - reference_chosen
    rejected = policy_rejected - reference_rejected
    logits = beta * (chosen - rejected)
    loss = -(1.0 - label_smoothing) * F.logsigmoid(logits) - label_smoothing * F.logsigmoid(-logits)
    return DPOTerms(loss, beta * chosen.detach(), beta * rejected.detach())


def posterior_kl(p: PhysicsPosterior, q: PhysicsPosterior) -> Tensor:  # [B]
    """Exact KL(p || q): categorical KL plus the two Gaussian KLs (the factors are independent)."""
    log_p, log_q = F.log_softmax(p.material_logits, -1), F.log_softmax(q.material_logits, -1)
    categorical = (log_p.exp() * (log_p - log_q)).sum(-1)

    def gaussian(m1: Tensor, lv1: Tensor, m2: Tensor, lv2: Tensor) -> Tensor:
        return 0.5 * (lv2 - lv1 + (lv1.exp() + (m1 - m2) ** 2) / lv2.exp() - 1.0)

    return (
        categorical
        + gaussian(p.z_E_mean, p.z_E_logvar, q.z_E_mean, q.z_E_logvar)
        + gaussian(p.z_nu_mean, p.z_nu_logvar, q.z_nu_mean, q.z_nu_logvar)
    )


def log10_E_shift(policy: PhysicsPosterior, reference: PhysicsPosterior) -> Tensor:  # []
    """Mean |log10 E| distance, decades, between the E each model would simulate: its posterior
    mean, read in its most likely material's range when E is relative to the material."""
    return (policy.log10_E_mean.detach() - reference.log10_E_mean).abs().mean()


def trained_part(model: PhysGM, path: str) -> torch.nn.Module:
    """The submodule of ``model`` at ``path`` that stage 2 trains: the physics head or a part of it.

    Only the physics head may train: the backbone, the Gaussian head and the gate feed it inputs
    that are computed once per scene and shared with the frozen reference (``LitDPO.head_inputs``).
    """
    if path != "physics_head" and not path.startswith("physics_head."):
        raise ValueError(
            f"stage.trainable={path!r}: stage 2 trains the physics head or a part of it, a path that "
            "starts with physics_head (physics_head, physics_head.young, physics_head.young.3, ...)"
        )
    try:
        return model.get_submodule(path)
    except AttributeError:
        parts = [n for n, _ in model.physics_head.named_modules() if n]
        raise ValueError(
            f"stage.trainable={path!r} is not a part of this model's physics head; its parts: "
            f"physics_head.{{{', '.join(parts)}}}"
        ) from None


def freeze(module: torch.nn.Module) -> torch.nn.Module:
    """No gradients and eval mode (dropout off, norms use their statistics)."""
    module.requires_grad_(False)
    return module.eval()


@dataclass
class HeadInputs:
    """What the frozen parts of a model hand its physics head and the fusion of its material
    distribution, for [B] scenes or (``scene``) one."""

    tokens: Tensor  # [B, G, D] the global tokens
    pooled: Tensor | None  # [B, P] pooled encoder features (a features classifier or a gate), or None
    log_prior: Tensor | None  # [B, M] the semantic prior (CNN encoder), or None
    gate: Tensor | None  # [B] the domain gate's P(real object), or None

    def parts(self) -> tuple[Tensor | None, ...]:
        return self.tokens, self.pooled, self.log_prior, self.gate

    def scene(self, k: int) -> HeadInputs:
        return HeadInputs(*(None if t is None else t[k].detach() for t in self.parts()))

    @staticmethod
    def stack(scenes: list[HeadInputs], device) -> HeadInputs:
        fields = zip(*(s.parts() for s in scenes), strict=True)
        return HeadInputs(*(None if t[0] is None else torch.stack(t).to(device) for t in fields))


class LitDPO(L.LightningModule):
    """PhysGM policy + frozen reference + the DPO loss on preference pairs.

    Args:
        model: ``PhysGMConfig.to_dict()``; None takes it from ``init_ckpt``.
        init_ckpt: the stage-1 checkpoint; the policy starts from it and the reference is a
            copy of it. When the file is absent (e.g. loading a DPO checkpoint elsewhere for
            inference) the policy is built from ``model`` and training refuses to start.
        loss: ``DPOLossConfig`` fields.  optim: ``OptimConfig`` fields.
        total_steps: optimiser steps of the run (length of the learning-rate schedule).
        inputs: the input views trained on (num_views, input_resolution, background), kept for
            evaluation (``physgm.train.evaluate_dpo``).
        prior_weight: the semantic prior weight w of the policy and the reference; None keeps the
            stage-1 checkpoint's. Procedural scenes need 0: their ImageNet classes say nothing about
            the material, so the prior a shipped model carries for real photos would pick it.
        trainable: the part of the physics head that trains, a submodule path of the model
            (``physics_head``, ``physics_head.young``, ``physics_head.young.3``, ...); the rest of
            the head stays frozen with the backbone and the Gaussian head.
        format_version: checkpoint layout version (``physgm.CHECKPOINT_FORMAT_VERSION``), checked on load.
    """

    def __init__(
        self,
        model: dict[str, Any] | None = None,
        init_ckpt: str | None = None,
        loss: dict[str, Any] | None = None,
        optim: dict[str, Any] | None = None,
        total_steps: int = 1000,
        inputs: dict[str, Any] | None = None,
        prior_weight: float | None = None,
        trainable: str = "physics_head",
        format_version: int = CHECKPOINT_FORMAT_VERSION,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        stage1 = load_model(init_ckpt)[0] if init_ckpt and Path(init_ckpt).is_file() else None
        if model is None:
            if stage1 is None:
                raise ValueError(
                    "LitDPO needs a model config or an existing stage-1 checkpoint, got "
                    f"init_ckpt={init_ckpt!r}"
                )
            model = stage1.config.to_dict()
        config = PhysGMConfig.from_dict(model)
        if prior_weight is not None:
            config = config.with_prior_weight(prior_weight)
        self.hparams["model"] = config.to_dict()  # stored so the DPO checkpoint rebuilds on its own
        self.model = PhysGM(config, load_pretrained=False)
        # A list, so the reference is not a submodule (not saved, not optimised).
        self._reference: list[PhysGM] = []
        if stage1 is not None:
            own = stage1.config if prior_weight is None else stage1.config.with_prior_weight(prior_weight)
            if own != config:
                raise ValueError(
                    f"the model config does not match the stage-1 checkpoint {init_ckpt}; drop the model "
                    "override"
                )
            self.model.load_state_dict(stage1.state_dict())
            self._reference.append(freeze(copy.deepcopy(self.model)))
        freeze(self.model.backbone)
        freeze(self.model.gaussian_head)
        self.model.physics_head.requires_grad_(False)
        trained_part(self.model, trainable).requires_grad_(True)
        # scene id -> what the frozen parts hand the physics head and its fusion (not saved)
        self._head_inputs: dict[str, HeadInputs] = {}
        self.loss_cfg = DPOLossConfig(**(loss or {}))
        self.optim_cfg = OptimConfig(**(optim or {}))
        self.total_steps = total_steps

    @property
    def reference(self) -> PhysGM:
        """The frozen stage-1 copy, on this module's device."""
        if not self._reference:
            raise RuntimeError(
                f"no frozen reference: the stage-1 checkpoint init_ckpt={self.hparams.init_ckpt!r} was not "
                "found when this module was built (DPO checkpoints never contain the reference); pass its "
                "path"
            )
        return self._reference[0].to(self.device)

    def train(self, mode: bool = True) -> LitDPO:
        # Lightning switches the whole module to train mode each epoch; the frozen parts stay in eval.
        super().train(mode)
        if hasattr(self, "model"):
            self.model.backbone.eval()
            self.model.gaussian_head.eval()
        return self

    def setup(self, stage: str) -> None:
        if stage == "fit":
            self.reference  # noqa: B018 - fail before any rollout when the reference is missing

    def configure_optimizers(self):
        trained = ((n, p) for n, p in self.model.physics_head.named_parameters() if p.requires_grad)
        opt, sched = build_optimizer(trained, self.optim_cfg, self.total_steps)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def train_dataloader(self):
        from physgm.train.rollout import RolloutCallback

        for cb in self.trainer.callbacks:
            if isinstance(cb, RolloutCallback):
                return cb.train_dataloader(self.trainer, self)
        raise RuntimeError(
            "LitDPO trains on pairs made by physgm.train.rollout.RolloutCallback; add one to the trainer's "
            "callbacks"
        )

    def transfer_batch_to_device(
        self, batch: DPOBatch, device: torch.device, dataloader_idx: int
    ) -> DPOBatch:
        return batch.to(device)

    def head_inputs(self, batch: DPOBatch) -> HeadInputs:  # [B, ...]
        """What the physics head and the fusion of its material distribution read for the batch's
        scenes, computed once per scene (``HeadInputs``).

        Exact, not an approximation: the backbone, the encoder and the gate are frozen and in eval
        mode, and the reference's are bit-identical copies, so both physics heads read the same inputs.
        """
        missing = [i for i, s in enumerate(batch.scenes) if s not in self._head_inputs]
        if missing:
            seen: list[tuple] = []
            hook = self.model.physics_head.register_forward_hook(lambda mod, args, out: seen.append(args))
            try:
                with torch.no_grad():
                    out = self.model(
                        batch.images[missing], batch.masks[missing], batch.c2w[missing], batch.Ks[missing]
                    )
            finally:
                hook.remove()
            found = HeadInputs(seen[0][0], seen[0][1], out.semantic_log_prior, out.domain_real)
            for k, i in enumerate(missing):
                self._head_inputs[batch.scenes[i]] = found.scene(k)
        return HeadInputs.stack([self._head_inputs[s] for s in batch.scenes], self.device)

    def posteriors(self, batch: DPOBatch) -> tuple[PhysicsPosterior, PhysicsPosterior]:
        """(policy, reference) physics posteriors [B] of the batch's scenes: what each model's forward
        gives (``PhysGM.fused_posterior``), from the cached head inputs."""
        x = self.head_inputs(batch)
        policy = self._posterior(self.model, x)
        with torch.no_grad():
            reference = self._posterior(self.reference, x)
        return policy, reference

    @staticmethod
    def _posterior(model: PhysGM, x: HeadInputs) -> PhysicsPosterior:
        head = model.physics_head(x.tokens, x.pooled)
        procedural = model.physics_head.procedural_logits(x.pooled)
        return model.fused_posterior(head, x.log_prior, x.gate, procedural)

    def log_prob(self, posterior: PhysicsPosterior, sample, batch: DPOBatch) -> Tensor:  # [B]
        """log pi of one [B, 1] sample: the exact joint, or its factorised form (see DPOLossConfig)."""
        if not self.loss_cfg.factorised:
            return posterior.log_prob(sample)[:, 0]
        material, log_E, log_nu = (t[:, 0] for t in posterior.log_prob_terms(sample))
        same = batch.winner.material[:, 0] == batch.loser.material[:, 0]
        return material + torch.where(same, log_E + log_nu, torch.zeros_like(log_E))

    def training_step(self, batch: DPOBatch, batch_idx: int) -> Tensor:
        policy, reference = self.posteriors(batch)
        pair = batch.has_pair
        pw, pl = self.log_prob(policy, batch.winner, batch), self.log_prob(policy, batch.loser, batch)
        rw, rl = self.log_prob(reference, batch.winner, batch), self.log_prob(reference, batch.loser, batch)
        terms = dpo_loss(
            pw[pair], pl[pair], rw[pair], rl[pair], self.loss_cfg.beta, self.loss_cfg.label_smoothing
        )
        kl = posterior_kl(policy, reference)  # [B] analytic KL(pi || pi_ref)
        loss = terms.loss.sum() / pair.sum().clamp_min(1)  # a batch of tie anchors only has no DPO term
        if self.loss_cfg.sft_weight > 0:
            loss = loss + self.loss_cfg.sft_weight * -(pw[pair].sum() / pair.sum().clamp_min(1))
        if self.loss_cfg.kl_weight > 0:
            loss = loss + self.loss_cfg.kl_weight * kl.mean()
        self._log_step(loss, terms, kl, pw[pair], pl[pair], policy, reference, batch)
        return loss

    def _log_step(
        self,
        loss,
        terms: DPOTerms,
        kl: Tensor,
        pw: Tensor,
        pl: Tensor,
        policy: PhysicsPosterior,
        reference: PhysicsPosterior,
        batch: DPOBatch,
    ) -> None:
        margins = terms.chosen_rewards - terms.rejected_rewards
        logs = {
            "train/loss": loss.detach(),
            "train/kl": kl.detach().mean(),
            "train/log10_E_shift": log10_E_shift(policy, reference),
        }
        if len(margins):
            logs.update(
                {
                    "train/dpo_loss": terms.loss.detach().mean(),
                    "rewards/chosen": terms.chosen_rewards.mean(),
                    "rewards/rejected": terms.rejected_rewards.mean(),
                    "rewards/margins": margins.mean(),
                    "rewards/accuracies": (margins > 0).float().mean(),
                    "train/logps_chosen": pw.detach().mean(),
                    "train/logps_rejected": pl.detach().mean(),
                    "train/distance_winner": batch.distance_winner[batch.has_pair].mean(),
                }
            )
            losers = batch.distance_loser[batch.has_pair]
            if torch.isfinite(losers).any():
                logs["train/distance_loser"] = losers[torch.isfinite(losers)].mean()
        self.log_dict(logs, batch_size=len(batch), on_step=True, on_epoch=True)

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        stray = [k for k in checkpoint["state_dict"] if not k.startswith("model.")]
        if stray:
            raise RuntimeError(f"DPO checkpoints hold only the policy (model.*); found {stray[:5]}")


def _merge_overrides(cfg, key: str, overrides) -> None:
    """Merge ``stage.<key>`` over the top-level group ``<key>`` (only nodes that exist there)."""
    from omegaconf import OmegaConf, open_dict

    if not overrides:
        return
    with open_dict(cfg):
        for name, value in overrides.items():
            if key == "callbacks":
                if cfg.callbacks and name in cfg.callbacks and cfg.callbacks[name] is not None:
                    cfg.callbacks[name] = OmegaConf.merge(cfg.callbacks[name], value)
            else:
                cfg[key][name] = value


def fit(cfg) -> dict[str, float]:
    """Train stage 2 from a Hydra config and return the last logged metrics."""
    from physgm.data.format import read_split
    from physgm.train.rollout import RolloutCallback, RolloutConfig
    from physgm.train.run import build_trainer, ensure_data, plain

    L.seed_everything(cfg.seed, workers=True)
    stage = cfg.stage
    init = str(stage.init_ckpt)
    if not Path(init).is_file():
        raise UserError(
            f"stage.init_ckpt={init} is not a file; pass a stage-1 checkpoint, e.g. "
            "stage.init_ckpt=outputs/<run>/checkpoints/last.ckpt (the default, the shipped "
            "checkpoints/physgm_tiny.ckpt, is found from the repository's root folder)"
        )
    rollout = plain(stage.rollout)
    data = plain(cfg.get("data")) or {}
    rollout["data_root"] = rollout.get("data_root") or data.get("root")
    try:  # before ensure_data, which may spend minutes generating a data set
        DPOLossConfig(**plain(stage.loss))
        OptimConfig(**plain(stage.optim))
        RolloutConfig(**rollout)
    except (TypeError, ValueError) as err:
        raise UserError(f"bad stage settings: {err}") from None
    ensure_data(cfg, rollout["data_root"], rollout["split"])
    rollout["input_resolution"] = rollout.get("input_resolution") or data.get("input_resolution")
    rollout["background"] = next(
        v for v in (rollout.get("background"), data.get("background"), 1.0) if v is not None
    )
    callback = RolloutCallback(**rollout)
    _merge_overrides(cfg, "trainer", stage.get("trainer"))
    _merge_overrides(cfg, "callbacks", stage.get("callbacks"))
    trainer = build_trainer(cfg, extra_callbacks=[callback])
    if trainer.reload_dataloaders_every_n_epochs != 1:
        raise UserError(
            "the DPO stage needs trainer.reload_dataloaders_every_n_epochs=1 (pairs change every round)"
        )
    scenes = len(read_split(callback.cfg.data_root, callback.cfg.split))
    if callback.cfg.max_scenes:
        scenes = min(scenes, callback.cfg.max_scenes)
    per_epoch = math.ceil(math.ceil(scenes / trainer.world_size) / callback.cfg.batch_size)
    total = trainer.max_steps if trainer.max_steps > 0 else max(1, trainer.max_epochs) * per_epoch
    warmup = int(stage.optim.get("warmup_steps", 0))
    # A fast_dev_run trains a batch or a few by design: its learning rate does not matter, only that
    # the code runs.
    if warmup >= total and not trainer.fast_dev_run:
        raise UserError(
            f"stage.optim.warmup_steps={warmup} is not below the {total} optimiser steps of this DPO "
            f"run, so the "
            "learning rate would never reach its peak (a stage-1 experiment's optimiser settings?); "
            "lower stage.optim.warmup_steps or use experiment=tiny_cpu_dpo"
        )
    inputs = {k: getattr(callback.cfg, k) for k in ("num_views", "input_resolution", "background")}
    try:  # every ValueError of the module's construction is about the stage's settings
        module = LitDPO(
            init_ckpt=init,
            loss=plain(stage.loss),
            optim=plain(stage.optim),
            total_steps=int(total),
            inputs=inputs,
            prior_weight=stage.get("prior_weight"),
            trainable=stage.get("trainable", "physics_head"),
        )
    except ValueError as err:
        raise UserError(str(err)) from None
    trainer.fit(module, ckpt_path=cfg.get("ckpt_path"))
    return {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1}
