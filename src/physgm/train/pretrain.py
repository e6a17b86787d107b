"""Stage 1: supervised pretraining of PhysGM (``python train.py stage=pretrain``)."""

from __future__ import annotations

import copy
import logging
import warnings
from typing import Any

import lightning as L
import torch
from torch import Tensor
from torchmetrics import MeanMetric

from physgm import CHECKPOINT_FORMAT_VERSION
from physgm.errors import UserError
from physgm.metrics.image import ImageMetrics, save_panel
from physgm.metrics.physics_metrics import PhysicsMetrics
from physgm.model.checkpoint import read_checkpoint
from physgm.model.config import PhysGMConfig
from physgm.model.physgm import PhysGM, PhysGMOutput
from physgm.render import rasterize_gaussians
from physgm.train.losses import PretrainLossConfig, pretrain_losses
from physgm.train.optim import OptimConfig, build_optimizer

log = logging.getLogger(__name__)

# What stage 1 trains (stage.trainable): everything; the Gaussian head of stage.init_ckpt alone;
# its backbone and Gaussian head ("geometry"), with the physics head frozen and loss.anchor holding
# the tokens it reads; or the Gaussian head and copies of the backbone's last stage.geometry_blocks
# blocks made for it ("geometry_blocks"), which leaves every physics output bit-identical.
TRAINABLE = ("all", "gaussian_head", "geometry", "geometry_blocks")
TRAINED_PARTS = {
    "gaussian_head": ("gaussian_head",),
    "geometry": ("gaussian_head", "backbone"),
    "geometry_blocks": ("gaussian_head", "backbone.geometry_blocks"),
}
VIEW_KEYS = ("v1", "v4")  # validation metrics are kept apart for 1 and 4 input views


def _within(name: str, parts: tuple[str, ...]) -> bool:
    """True when the parameter or module ``name`` is one of ``parts`` or inside one of them."""
    return any(name == part or name.startswith(part + ".") for part in parts)


def render_targets(
    out: PhysGMOutput,
    target_c2w: Tensor,  # [B, T, 4, 4]
    target_Ks: Tensor,  # [B, T, 3, 3]
    width: int,
    height: int,
    renderer: dict[str, Any],
) -> tuple[Tensor, Tensor]:  # [B, T, H, W, 3], [B, T, H, W, 1]
    """Render each scene's predicted Gaussians from its target cameras on a white background."""
    g = out.gaussians
    viewmats = torch.linalg.inv(target_c2w)
    background = torch.ones(3, dtype=g.means.dtype, device=g.means.device)
    rgb, alpha, _ = rasterize_gaussians(
        g, viewmats, target_Ks, width, height, background=background, **renderer
    )
    return rgb, alpha


class LitPretrain(L.LightningModule):
    """PhysGM plus its stage-1 losses, metrics and optimiser.

    All constructor arguments are plain dicts, so ``LitPretrain.load_from_checkpoint(path)`` works
    outside Hydra. The LPIPS network is held outside the module tree and never saved.
    """

    def __init__(
        self,
        model: dict[str, Any] | None = None,
        loss: dict[str, Any] | None = None,
        optim: dict[str, Any] | None = None,
        renderer: dict[str, Any] | None = None,
        total_steps: int = 1000,
        format_version: int = CHECKPOINT_FORMAT_VERSION,
        trainable: str = "all",
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        if trainable not in TRAINABLE:
            raise ValueError(f"stage.trainable must be one of {TRAINABLE}, got {trainable!r}")
        config = PhysGMConfig.from_dict(model or {})
        self.model = PhysGM(config)
        if trainable in TRAINED_PARTS:  # the physics head is frozen; with gaussian_head, so are its inputs
            trained = TRAINED_PARTS[trainable]
            for name, p in self.model.named_parameters():
                p.requires_grad_(p.requires_grad and _within(name, trained))
        self.loss_cfg = PretrainLossConfig(**(loss or {}))
        self.optim_cfg = OptimConfig(**(optim or {}))
        self.renderer = dict(renderer or {"backend": "warp"})
        self.total_steps = total_steps
        m = config.physics_head.num_materials
        self.val_physics = torch.nn.ModuleDict({key: PhysicsMetrics(m) for key in VIEW_KEYS})
        self.val_images = torch.nn.ModuleDict({key: ImageMetrics() for key in VIEW_KEYS})
        self.val_loss = torch.nn.ModuleDict({key: MeanMetric() for key in VIEW_KEYS})
        self._lpips: list[torch.nn.Module] = []  # a list, so the frozen LPIPS net is not a submodule
        self._reference: list[PhysGM] = []  # the frozen starting model of loss.anchor (a list: not saved)

    # -- setup -------------------------------------------------------------------------------
    def setup(self, stage: str) -> None:
        if self.loss_cfg.lpips > 0 and not self._lpips:
            from physgm.metrics.lpips import load_lpips

            self._lpips.append(load_lpips(self.loss_cfg.lpips_net, self.loss_cfg.lpips_backbone_path))

    @property
    def lpips_model(self) -> torch.nn.Module | None:
        if not self._lpips:
            return None
        self._lpips[0].to(self.device)
        return self._lpips[0]

    def train(self, mode: bool = True) -> LitPretrain:
        super().train(mode)
        trained = TRAINED_PARTS.get(self.hparams.get("trainable"))
        if trained is not None and mode:  # every frozen part stays in eval mode
            for name, module in self.model.named_modules():
                holds_trained = any(_within(part, (name,)) for part in trained)
                if name and not holds_trained and not _within(name, trained):
                    module.eval()
        return self

    def anchor_to_start(self) -> None:
        """Keep a frozen copy of the model as it is now (the warm start) for ``loss.anchor``: never
        trained, never in the checkpoint."""
        self._reference[:] = [copy.deepcopy(self.model).requires_grad_(False).eval()]

    def configure_optimizers(self):
        params = [(n, p) for n, p in self.model.named_parameters() if p.requires_grad]
        opt, sched = build_optimizer(params, self.optim_cfg, self.total_steps)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    # -- steps -------------------------------------------------------------------------------
    def forward(self, batch) -> PhysGMOutput:
        return self.model(batch.images, batch.masks, batch.c2w, batch.Ks, batch.features)

    def _losses(self, batch) -> tuple[PhysGMOutput, Tensor, Tensor, dict[str, Tensor]]:
        out = self(batch)
        reference = None
        if self.loss_cfg.anchor > 0 and self._reference:
            with torch.no_grad():
                start = self._reference[0].to(self.device)
                reference = start.global_tokens(batch.images, batch.c2w, batch.Ks, batch.features)
        h, w = batch.target_images.shape[-2:]
        rgb, alpha = render_targets(out, batch.target_c2w, batch.target_Ks, w, h, self.renderer)
        terms = pretrain_losses(
            self.loss_cfg,
            rgb,
            alpha,
            batch.target_images,
            batch.target_masks,
            out.physics,
            batch.material,
            batch.log10_E,
            batch.nu,
            self.lpips_model,
            scales=out.gaussians.scales,
            valid=out.gaussians.valid,
            means=out.gaussians.means,
            surface_points=batch.surface_points,
            surface_known=batch.surface_known,
            tokens=out.global_tokens,
            reference_tokens=reference,
        )
        return out, rgb, alpha, terms

    def training_step(self, batch, batch_idx: int) -> Tensor:
        out, _, _, terms = self._losses(batch)
        bsz = batch.images.shape[0]
        self.log_dict({f"train/{k}": v.detach() for k, v in terms.items() if k != "loss"}, batch_size=bsz)
        self.log("train/loss", terms["loss"].detach(), batch_size=bsz, prog_bar=True)
        self.log("train/gaussians", out.gaussians.count.float().mean(), batch_size=bsz)
        return terms["loss"]

    def validation_step(self, batch, batch_idx: int, dataloader_idx: int = 0) -> None:
        out, rgb, _, terms = self._losses(batch)
        views = batch.images.shape[1]
        key = f"v{views}"
        bsz = batch.images.shape[0]
        self.val_loss[key].update(terms["loss"].detach(), bsz)
        pred = rgb.permute(0, 1, 4, 2, 3).clamp(0, 1)
        novel = slice(
            views, None
        )  # the first V targets are the inputs; score only views the model did not see
        if key in self.val_images and pred.shape[1] > views:
            self.val_images[key].update(
                pred[:, novel].flatten(0, 1), batch.target_images[:, novel].flatten(0, 1)
            )
        known = batch.true_known  # real assets have annotations only; score physics against the truth
        if key in self.val_physics and known.any():
            self.val_physics[key].update(
                out.physics[known],
                batch.true_material[known],
                batch.true_log10_E[known],
                batch.true_nu[known],
            )
        if batch_idx == 0 and self.trainer.is_global_zero:
            save_panel(self, batch.images[0], pred[0], batch.target_images[0], tag=f"val_{key}")

    def on_validation_epoch_end(self) -> None:
        # compute() gathers a metric's state from every rank, so every rank must call it for the same
        # metrics in the same order. A batch's view count follows from its asset ids, so under DDP one
        # rank may have seen only 1-view batches and another only 4-view ones: deciding per rank hung
        # (2 CPU processes, gloo). The decision is taken on the counts summed over ranks.
        parts = {"loss": self.val_loss, "images": self.val_images, "physics": self.val_physics}
        metrics = [(key, part, parts[part][key]) for key in VIEW_KEYS for part in parts]
        seen = torch.tensor([float(m.update_count) for _, _, m in metrics], device=self.device)
        seen = self.trainer.strategy.reduce(seen, reduce_op="sum")
        for (key, part, metric), count in zip(metrics, seen.tolist(), strict=True):
            if count > 0:
                # a rank without such batches adds an empty state to the gather (torchmetrics warns)
                with warnings.catch_warnings():
                    warnings.filterwarnings("ignore", message=".*compute.*before.*update.*")
                    values = metric.compute()
                if part == "loss":
                    values = {"loss": values}
                values.pop("confusion", None)
                for name, value in values.items():
                    # the value is already the all-rank one; sync_dist keeps Lightning's epoch
                    # reduction honest
                    self.log(f"val/{key}/{name}", value, sync_dist=True)
            metric.reset()


def fit(cfg) -> dict[str, float]:
    """Train stage 1 from a Hydra config and return the last validation metrics."""
    from hydra.utils import instantiate

    from physgm.train.run import build_trainer, ensure_data, plain

    # Settings are checked before ensure_data, which may spend minutes generating a data set.
    try:
        PretrainLossConfig(**plain(cfg.stage.loss))
        OptimConfig(**plain(cfg.stage.optim))
    except (TypeError, ValueError) as err:
        raise UserError(f"bad stage settings: {err}") from None
    trainable = cfg.stage.get("trainable", "all")
    if trainable not in TRAINABLE:
        raise UserError(f"stage.trainable must be one of {', '.join(TRAINABLE)}, got {trainable!r}")
    model = plain(cfg.model)
    if cfg.stage.loss.get("anchor", 0) > 0 and trainable != "geometry":
        raise UserError(
            "stage.loss.anchor holds the tokens of the starting model while the backbone trains: it "
            "needs stage.trainable=geometry and stage.init_ckpt=PATH"
        )
    if trainable in TRAINED_PARTS:
        if not cfg.stage.get("init_ckpt"):
            raise UserError(
                f"stage.trainable={trainable} fine-tunes the Gaussians of a trained model; give it "
                "with stage.init_ckpt=PATH"
            )
        model = read_checkpoint(cfg.stage.init_ckpt).hparams["model"]  # its physics settings whole
        if trainable == "geometry_blocks":
            model = _with_geometry_blocks(model, int(cfg.stage.get("geometry_blocks", 0)))
        if cfg.stage.get("gaussian_layers") is not None:
            model = _with_gaussian_layers(model, int(cfg.stage.gaussian_layers))
    L.seed_everything(cfg.seed, workers=True)
    ensure_data(cfg)
    datamodule = instantiate(cfg.data)
    module = LitPretrain(
        model=model,
        loss=plain(cfg.stage.loss),
        optim=plain(cfg.stage.optim),
        renderer=plain(cfg.renderer),
        total_steps=int(cfg.trainer.max_steps),
        trainable=trainable,
    )
    if cfg.stage.get("init_ckpt"):
        from physgm.train.warm_start import warm_start

        log.info(warm_start(module.model, cfg.stage.init_ckpt).summary())
        if trainable == "geometry" and module.loss_cfg.anchor > 0:
            module.anchor_to_start()
    trainer = build_trainer(cfg)
    trainer.fit(module, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"))
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1}
    if trainer.is_global_zero:
        from physgm.train.sweep import write_run_summary

        write_run_summary(cfg.paths.output_dir, module.model, metrics, trainer.global_step, _overrides())
    return metrics


def _with_geometry_blocks(model: dict[str, Any], count: int) -> dict[str, Any]:
    """A checkpoint's model config whose backbone gives the Gaussian head ``count`` blocks of its own."""
    backbone = model["backbone"]
    depth, had = backbone["depth"], backbone.get("geometry_blocks", 0)
    if not 1 <= count <= depth:
        raise UserError(
            f"stage.trainable=geometry_blocks trains copies of the backbone's last stage.geometry_blocks "
            f"blocks; give 1 to {depth} (the backbone's depth), got {count}"
        )
    if count < had:
        raise UserError(
            f"stage.init_ckpt already gives the Gaussian head its own last {had} blocks, and trained "
            f"copies cannot be dropped; set stage.geometry_blocks={had} to train them further, or more "
            "to give it copies of earlier blocks too"
        )
    return {**model, "backbone": {**backbone, "geometry_blocks": count}}


def _with_gaussian_layers(model: dict[str, Any], layers: int) -> dict[str, Any]:
    """A checkpoint's model config whose Gaussian head puts ``layers`` Gaussians on each pixel ray."""
    head = model["gaussian_head"]
    had = head.get("layers", 1)
    if layers < had:
        raise UserError(
            f"stage.gaussian_layers={layers}, but stage.init_ckpt already has {had} Gaussian layers; "
            f"give {had} or more (a layer is added, never dropped)"
        )
    return {**model, "gaussian_head": {**head, "layers": layers}}


def _overrides() -> list[str]:
    """The command-line overrides of this Hydra run (none outside Hydra)."""
    from hydra.core.hydra_config import HydraConfig

    try:
        return list(HydraConfig.get().overrides.task)
    except ValueError:  # not launched by Hydra (tests, notebooks)
        return []
