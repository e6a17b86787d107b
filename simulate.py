"""Photo to 4D clip: ``python simulate.py input=examples/jelly_cube.png [scene=drop]`` (physgm.pipeline)."""

import hydra
from omegaconf import DictConfig

# before anything loads torch: physgm sets GOMP_SPINCOUNT, which torch's OpenMP reads only then
import physgm  # noqa: F401


@hydra.main(version_base="1.3", config_path="conf", config_name="simulate")
def main(cfg: DictConfig) -> None:
    from physgm.pipeline import run

    run(cfg)


if __name__ == "__main__":
    main()
