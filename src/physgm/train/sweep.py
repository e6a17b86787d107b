"""Speed against error: one summary per training run, one table and one plot per Hydra multirun.

    python train.py -m experiment=sweep_cpu            # trains the grid, then writes the table
    python -m physgm.train.sweep outputs/sweep_cpu/<time>   # rebuild the table (e.g. after a crash)

Every stage-1 run writes ``summary.json`` in its folder (``write_run_summary``): the overrides
that made it, parameters, CPU forward milliseconds of one 4-view scene at its input size, and
the last validation metrics. ``SweepTable``, a Hydra callback, gathers the summaries of a
multirun into ``sweep.csv``, ``sweep.md`` and ``sweep.png`` (forward time against PSNR and
material accuracy) in the sweep folder.
"""

from __future__ import annotations

import csv
import json
import logging
import statistics
import sys
from pathlib import Path
from typing import Any

import torch
from hydra.experimental.callback import Callback

log = logging.getLogger(__name__)

SUMMARY = "summary.json"
COLUMNS = [  # (key in the summary's flat row, header)
    ("overrides", "overrides"),
    ("parameters", "parameters"),
    ("input_resolution", "input px"),
    ("forward_ms", "CPU forward ms (4 views, 1 thread)"),
    ("steps", "steps"),
    ("val/v4/psnr", "PSNR 4 views"),
    ("val/v1/psnr", "PSNR 1 view"),
    ("val/v4/material_acc", "material acc 4 views"),
    ("val/v1/material_acc", "material acc 1 view"),
    ("val/v4/abs_log10E_median", "median abs dlog10E 4 views"),
]


def write_run_summary(
    output_dir: str | Path,
    model,
    metrics: dict[str, float],
    steps: int,
    overrides: list[str],
    repeats: int = 10,
) -> Path:
    """Time the trained model's forward on one thread and write ``summary.json`` next to the run."""
    from physgm.model.timing import count_parameters, forward_milliseconds

    size = model.config.backbone.encoder.img_size
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # comparable across runs and machines with other work on the cores
    try:
        timings = forward_milliseconds(model, 4, size, repeats)
    finally:
        torch.set_num_threads(threads)
    summary = {
        "overrides": " ".join(overrides),
        "parameters": count_parameters(model)["total"],
        "input_resolution": size,
        "forward_ms": statistics.median(timings),
        "forward_ms_spread": [min(timings), max(timings)],
        "steps": steps,
        **{k: v for k, v in metrics.items() if k.startswith("val/")},
    }
    path = Path(output_dir) / SUMMARY
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(summary, indent=2))
    tmp.replace(path)
    return path


def collect(sweep_dir: str | Path) -> list[dict[str, Any]]:
    """The run summaries under ``sweep_dir``, fastest model first."""
    rows = [json.loads(p.read_text()) for p in sorted(Path(sweep_dir).glob(f"*/{SUMMARY}"))]
    return sorted(rows, key=lambda r: r["forward_ms"])


def _cell(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, int) and value > 10_000:
        return f"{value / 1e6:.2f}M"
    return "—" if value is None else str(value)


def write_table(sweep_dir: str | Path) -> dict[str, Path]:
    """``sweep.csv``, ``sweep.md`` and ``sweep.png`` from the run summaries in ``sweep_dir``."""
    sweep_dir = Path(sweep_dir)
    rows = collect(sweep_dir)
    if not rows:
        raise FileNotFoundError(f"no {SUMMARY} under {sweep_dir}/*/: did the sweep's runs finish?")
    keys = [k for k, _ in COLUMNS]
    with open(sweep_dir / "sweep.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(keys)
        writer.writerows([[r.get(k) for k in keys] for r in rows])
    lines = ["| " + " | ".join(h for _, h in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(_cell(r.get(k)) for k in keys) + " |" for r in rows]
    (sweep_dir / "sweep.md").write_text("\n".join(lines) + "\n")
    plot(rows, sweep_dir / "sweep.png")
    return {"csv": sweep_dir / "sweep.csv", "md": sweep_dir / "sweep.md", "png": sweep_dir / "sweep.png"}


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    """Forward time against PSNR (left) and material accuracy (right), 4 views solid, 1 view hollow."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    ms = [r["forward_ms"] for r in rows]
    for ax, metric, label in (
        (axes[0], "psnr", "novel-view PSNR (dB)"),
        (axes[1], "material_acc", "material accuracy"),
    ):
        for views, style in (
            (4, dict(marker="o")),
            (1, dict(marker="o", facecolors="none", edgecolors="C0")),
        ):
            ys = [r.get(f"val/v{views}/{metric}") for r in rows]
            pts = [(x, y) for x, y in zip(ms, ys, strict=True) if y is not None]
            if pts:
                ax.scatter(*zip(*pts, strict=True), label=f"{views} view{'s' if views > 1 else ''}", **style)
        for r in rows:
            y = r.get(f"val/v4/{metric}")
            if y is not None:
                ax.annotate(
                    f"{r['parameters'] / 1e6:.1f}M, {r['input_resolution']}px",
                    (r["forward_ms"], y),
                    fontsize=7,
                    xytext=(4, 4),
                    textcoords="offset points",
                )
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())  # 20, 50, 100 rather than 2x10^1
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("CPU forward of one 4-view scene (ms, 1 thread)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend()
    fig.savefig(path, dpi=120)
    plt.close(fig)


class SweepTable(Callback):
    """Hydra callback: after a multirun, write the table and the plot into the sweep folder."""

    def on_multirun_end(self, config, **kwargs) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        try:
            paths = write_table(sweep_dir)
        except FileNotFoundError as err:
            log.error("%s", err)
            return
        log.info("sweep table: %s", ", ".join(str(p) for p in paths.values()))


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m physgm.train.sweep SWEEP_DIR", file=sys.stderr)
        return 2
    for kind, path in write_table(args[0]).items():
        print(f"{kind}: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
