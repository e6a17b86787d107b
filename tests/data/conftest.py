"""Shared tiny data sets for the data tests (32 px views, a few hundred Gaussians)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from physgm.data.synth import SynthConfig, generate

TINY = dict(resolution=32, gaussians=600, video_fraction=0.0)


def tiny_config(count: int, seed: int = 0, **overrides) -> SynthConfig:
    return SynthConfig(count=count, seed=seed, **{**TINY, **overrides})


@pytest.fixture(scope="session")
def make_config():
    """``make_config(count, seed=0, **overrides)`` -> a tiny SynthConfig."""
    return tiny_config


@pytest.fixture(scope="session")
def tiny_root(tmp_path_factory) -> Path:
    """24 synthetic assets with their split lists; tests that modify it must copy it first."""
    root = tmp_path_factory.mktemp("tiny") / "synthetic"
    summary = generate(tiny_config(24, seed=3), root, workers=1, progress=False)
    assert summary["done"] == 24 and summary["failed"] == 0, summary["failures"]
    return root


@pytest.fixture
def tiny_copy(tiny_root, tmp_path) -> Path:
    """A private copy of the tiny data set that a test may damage."""
    dst = tmp_path / "copy"
    shutil.copytree(tiny_root, dst)
    return dst
