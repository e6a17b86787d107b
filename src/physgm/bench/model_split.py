"""The two inputs the model benchmarks share, checked before any work: a checkpoint and a data split."""

from __future__ import annotations

from pathlib import Path

from physgm.errors import UserError


def check_model_and_split(ckpt: Path, data: Path, split: str, make: str) -> None:
    """A missing checkpoint or split is a ``UserError``; ``make`` says how to make such a data set."""
    if not ckpt.is_file():
        raise UserError(f"checkpoint {ckpt} not found")
    if not (data / "splits" / f"{split}.txt").is_file():
        raise UserError(f"{data} has no split {split!r} (splits/{split}.txt); make a data set with {make}")
