"""Checkpointing for both training stages: a resume point that is never stale.

Lightning's ``ModelCheckpoint`` writes ``last.ckpt`` only at its interval, and at the end of
training only if it never wrote one. A run stopped by ``trainer.max_time`` (how the CPU
experiments end) therefore kept a ``last.ckpt`` up to ``every_n_train_steps - 1`` steps old:
the shipped tiny model was step 4400 of 4470.
"""

from __future__ import annotations

import lightning.pytorch as pl
from lightning.pytorch.callbacks import ModelCheckpoint


class ResumeCheckpoint(ModelCheckpoint):
    """``ModelCheckpoint`` that also refreshes ``last.ckpt`` when training ends between two saves."""

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        # The skip test is Lightning's own: fast_dev_run, sanity check, or this step already saved.
        if self.save_last and not self._should_skip_saving_checkpoint(trainer):
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
        super().on_train_end(trainer, pl_module)
