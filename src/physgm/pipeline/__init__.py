"""Photo -> physically simulated 4D clip (``python simulate.py input=photo.png``).

Layout:
    config          typed run settings from conf/simulate.yaml
    prepared_input  photo, posed views or .ply -> model inputs
    physics_choice  posterior mean / samples / overrides
    staging         physical size, placement, output camera, floor
    outputs         atomic run folder, videos, contact sheet, JSON
    stages          the stages

``run(cfg)`` is the Hydra entry; ``execute(RunConfig)`` the plain-Python one.
"""

from physgm.errors import UserError
from physgm.pipeline.config import RunConfig, from_hydra
from physgm.pipeline.stages import STAGES, execute, run

__all__ = ["STAGES", "RunConfig", "UserError", "execute", "from_hydra", "run"]
