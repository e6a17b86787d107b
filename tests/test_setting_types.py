"""Settings of the wrong type stop with a message that names them (physgm.setting_types.check_types)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from physgm.sim.mpm.stepping import SolverConfig
from physgm.sim.planner.config import PlannerConfig
from physgm.train.dpo import DPOLossConfig
from physgm.train.losses import PretrainLossConfig
from physgm.train.optim import OptimConfig

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(
    ("make", "message"),
    [
        # Before: "maybe" is a true string, so the planner ran with the rigid path allowed.
        (
            lambda: PlannerConfig(allow_rigid="maybe"),
            "planner setting allow_rigid='maybe' must be true or false",
        ),
        (lambda: PlannerConfig(coast=1), "planner setting coast=1 must be true or false"),
        # Before: a TypeError about '<' between a str and an int, naming no setting.
        (lambda: SolverConfig(cfl="fast"), "solver setting cfl='fast' must be a number"),
        (lambda: PlannerConfig(bound_px=True), "planner setting bound_px=True must be a number"),
        (lambda: PlannerConfig(cells_across=12.5), "planner setting cells_across=12.5 must be an integer"),
        (lambda: SolverConfig(graphs="no"), "solver setting graphs='no' must be true or false"),
        (lambda: OptimConfig(lr="fast"), "optim setting lr='fast' must be a number"),
        (lambda: DPOLossConfig(factorised="yes"), "loss setting factorised='yes' must be true or false"),
        (
            lambda: PretrainLossConfig(surface_max_gaussians=1.5),
            "loss setting surface_max_gaussians=1.5 must be",
        ),
    ],
)
def test_a_setting_of_the_wrong_type_is_named(make, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        make()


def test_numbers_of_any_kind_are_numbers():
    cfg = PlannerConfig(bound_px=1, cfl=np.float32(0.3), cells_across=np.int64(16), max_cells=96.0)
    assert cfg.bound_px == 1 and cfg.cells_across == 16
    assert SolverConfig(cfl=1, max_substeps=10).cfl == 1


def test_the_pipeline_says_which_setting_was_wrong():
    from physgm.errors import UserError
    from physgm.pipeline.stages import _planner

    cfg = type("C", (), {"planner": {"allow_rigid": "maybe"}})()
    with pytest.raises(
        UserError, match="bad planner settings: planner setting allow_rigid='maybe' must be true"
    ):
        _planner(cfg)


@pytest.mark.parametrize(
    "overrides", [["stage=pretrain"], ["stage=dpo"], ["experiment=tiny_cpu"], ["experiment=tiny_cpu_dpo"]]
)
def test_the_shipped_training_settings_have_their_types(overrides):
    # None passes the check (several settings take null for "the default"), so the shipped YAMLs build.
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from physgm.train.rollout import RolloutConfig

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        stage = OmegaConf.to_container(compose("train", overrides=overrides).stage, resolve=True)
    OptimConfig(**stage["optim"])
    if "rollout" in stage:
        DPOLossConfig(**stage["loss"])
        assert RolloutConfig(**stage["rollout"]).sim.budget.max_seconds > 0
    else:
        PretrainLossConfig(**stage["loss"])
