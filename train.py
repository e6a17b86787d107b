"""Train PhysGM: ``python train.py stage=pretrain`` or ``python train.py stage=dpo stage.init_ckpt=...``."""

import hydra
from omegaconf import DictConfig

# before anything loads torch: physgm sets GOMP_SPINCOUNT, which torch's OpenMP reads only then
import physgm  # noqa: F401


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
def main(cfg: DictConfig) -> None:
    from physgm.train.run import main as train

    train(cfg)


if __name__ == "__main__":
    main()
