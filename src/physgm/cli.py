"""Console scripts ``physgm-simulate``, ``physgm-train`` and ``physgm-view`` (``[project.scripts]``).

They take the same Hydra overrides as ``python simulate.py`` / ``python train.py`` in the
checkout, but compose the config tree shipped inside the package, so they work from any folder
after ``pip install``. Relative paths (``input=``, ``paths.output_dir``) resolve against the
folder they are launched from.
"""

from __future__ import annotations

import sys
from collections.abc import Callable

from omegaconf import DictConfig

import physgm  # noqa: F401  (sets GOMP_SPINCOUNT before anything loads torch)
from physgm.resources import conf_dir


def _hydra_entry(config_name: str, run: Callable[[DictConfig], None]) -> None:
    import hydra

    # An absolute config_path: Hydra then ignores the location of this file.
    hydra.main(version_base="1.3", config_path=str(conf_dir()), config_name=config_name)(run)()


def _simulate(cfg: DictConfig) -> None:
    from physgm.pipeline import run

    run(cfg)


def _train(cfg: DictConfig) -> None:
    from physgm.train.run import main

    main(cfg)


def simulate() -> None:
    """``physgm-simulate input=photo.png [scene=drop ...]``: the photo-to-4D pipeline."""
    _hydra_entry("simulate", _simulate)


def train() -> None:
    """``physgm-train stage=pretrain [experiment=tiny_cpu ...]``: training."""
    _hydra_entry("train", _train)


def view() -> None:
    """``physgm-view RUN_DIR``: the browser viewer of a simulate.py run (``python -m physgm.view``)."""
    from physgm.view.__main__ import main

    sys.exit(main())
