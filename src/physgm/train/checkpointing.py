"""Checkpointing for both training stages: a resume point that is never stale.

Lightning's ``ModelCheckpoint`` writes ``last.ckpt`` only at its interval, and at the end of
training only if it never wrote one. A run stopped by ``trainer.max_time`` (how the CPU
experiments end) therefore kept a ``last.ckpt`` up to ``every_n_train_steps - 1`` steps old.
And Lightning 2.6 writes ``last.ckpt`` at an epoch end only together with a top-k checkpoint,
which this resume point never keeps (``save_top_k: 0``): the epoch-based DPO stage had no
checkpoint until training ended.
"""

from __future__ import annotations

import lightning.pytorch as pl
from lightning.pytorch.callbacks import ModelCheckpoint


class ResumeCheckpoint(ModelCheckpoint):
    """``ModelCheckpoint`` that also refreshes ``last.ckpt`` when training ends between two saves,
    and at every ``every_n_epochs`` epoch end whether or not a top-k checkpoint was saved."""

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        super().on_train_epoch_end(trainer, pl_module)
        due = self._every_n_epochs >= 1 and (trainer.current_epoch + 1) % self._every_n_epochs == 0
        if (
            self.save_last
            and due
            and not self._should_skip_saving_checkpoint(trainer)
            and self._should_save_on_train_epoch_end(trainer)
        ):
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        # The skip test is Lightning's own: fast_dev_run, sanity check, or this step already saved.
        if self.save_last and not self._should_skip_saving_checkpoint(trainer):
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
        super().on_train_end(trainer, pl_module)
