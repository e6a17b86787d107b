"""Photo -> physically simulated 4D clip (``python simulate.py input=photo.png``).

Layout:
    config          typed run settings from conf/simulate.yaml, the scene's settings
    prepared_input  photo, posed views or .ply -> model inputs
    physics_choice  posterior mean / samples / overrides
    staging         physical size, placement, output camera, floor
    outputs         atomic run folder, videos, contact sheet, JSON
    stages          the stages

``run(cfg)`` is the Hydra entry; ``run_pipeline(RunConfig) -> RunResult`` the plain-Python one
(report.json's contents and each simulated future, typed).
"""

from physgm.errors import UserError
from physgm.pipeline.config import RunConfig, from_hydra
from physgm.pipeline.stages import STAGES, FutureResult, RunResult, run, run_pipeline

__all__ = [
    "STAGES",
    "FutureResult",
    "RunConfig",
    "RunResult",
    "UserError",
    "from_hydra",
    "run",
    "run_pipeline",
]
