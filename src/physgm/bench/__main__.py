"""``python -m physgm.bench SUITE [args]``: run one benchmark suite and print its JSON."""

from __future__ import annotations

import importlib
import sys

# Suite name -> module with a ``main(argv: list[str]) -> dict`` function.
SUITES = {
    "render": "physgm.bench.render_speed",
    "sim": "physgm.bench.sim_speed",
    "sim-verify": "physgm.bench.sim_verify",
    "sim-stability": "physgm.bench.sim_stability",
    "sim-substep": "physgm.bench.sim_substep",
    "e2e": "physgm.bench.e2e",
    "capture": "physgm.bench.capture",
    "model": "physgm.bench.model_speed",
    "hull": "physgm.bench.hull_speed",
    "dpo-landscape": "physgm.bench.dpo_landscape",
    "material-probe": "physgm.bench.material_probe",
    "stiffness-probe": "physgm.bench.stiffness_probe",
    "clips": "physgm.bench.clips",
    "volume": "physgm.bench.volume",
    "depth": "physgm.bench.depth",
}


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] not in SUITES:
        names = ", ".join(SUITES)
        sys.exit(f"usage: python -m physgm.bench SUITE [args]; SUITE is one of: {names}")
    importlib.import_module(SUITES[argv[0]]).main(argv[1:])


if __name__ == "__main__":
    main()
