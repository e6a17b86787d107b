"""Photo -> physically simulated 4D clip (``python simulate.py input=photo.png``).

Layout:
    config          typed run settings from conf/simulate.yaml
    prepared_input  photo, posed views or .ply -> model inputs
    checkpoint      loading with a compatibility check
    physics_choice  posterior mean / samples / overrides
    staging         physical size, placement, output camera, floor
    frames          a simulated trajectory rendered into frames
    outputs         atomic run folder, videos, contact sheet, JSON
    stages          the stages

``run(cfg)`` is the Hydra entry; ``execute(RunConfig)`` the plain-Python one.
"""

from physgm.pipeline.config import RunConfig, from_hydra
from physgm.pipeline.errors import UserError
from physgm.pipeline.stages import STAGES, execute, run

__all__ = ["STAGES", "RunConfig", "UserError", "execute", "from_hydra", "run"]
