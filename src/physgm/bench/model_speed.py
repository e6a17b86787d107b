"""Model benchmark: parameter counts and CPU forward time per model config; prints one JSON object.

    python -m physgm.bench model [--configs physgm,physgm_small,physgm_paper] [--views 4]
                                 [--max-px 256] [--repeats 5] [--threads 0]

Each config runs at its native resolution (``encoder.img_size``) capped at ``--max-px``. DINOv3
configs are built with random weights (``load_pretrained=False``): timing needs no checkpoint.
Wall-clock numbers are noisy when other processes share the CPU.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path
from typing import Any

import torch

from physgm.model.config import PhysGMConfig
from physgm.model.physgm import PhysGM
from physgm.model.timing import count_parameters, forward_milliseconds
from physgm.resources import conf_dir

CONF_DIR = conf_dir()


def load_config(name: str, conf_dir: Path = CONF_DIR) -> PhysGMConfig:
    """Compose ``conf/model/<name>.yaml`` with Hydra and map it onto ``PhysGMConfig``."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(conf_dir), version_base="1.3"):
        cfg = compose(config_name=None, overrides=[f"+model={name}"])
    return PhysGMConfig.from_dict(OmegaConf.to_container(cfg.model, resolve=True))


def bench_config(name: str, views: int, max_px: int, repeats: int) -> dict[str, Any]:
    config = load_config(name)
    torch.manual_seed(0)
    model = PhysGM(config, load_pretrained=False).eval()
    patch = model.patch_size
    size = max(patch, min(config.backbone.encoder.img_size, max_px) // patch * patch)
    timings = forward_milliseconds(model, views, size, repeats)
    return {
        "config": name,
        "encoder": config.backbone.encoder.kind,
        "views": views,
        "resolution": size,
        "native_resolution": config.backbone.encoder.img_size,
        "tokens": config.backbone.num_global_tokens + views * (size // patch) ** 2,
        "parameters": count_parameters(model),
        "forward_ms_median": statistics.median(timings),
        "forward_ms_min": min(timings),
        "runs": len(timings),
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m physgm.bench model", description=__doc__.split("\n")[0])
    parser.add_argument(
        "--configs", default="physgm,physgm_small,physgm_paper", help="comma-separated conf/model names"
    )
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--max-px", type=int, default=256, help="cap on the input resolution, px")
    parser.add_argument(
        "--repeats", type=int, default=5, help="timed forwards after one warm-up (0: time the only run)"
    )
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: leave torch's default)")
    args = parser.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    report = {
        "suite": "model",
        "torch_threads": torch.get_num_threads(),
        "results": [
            bench_config(name, args.views, args.max_px, args.repeats) for name in args.configs.split(",")
        ],
    }
    print(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
