"""``python -m physgm.bench sim-verify``: the MPM solver against analytic results.

Prints ``{"cases": [{"name", "error", "tolerance", "passed", ...}], "summary": {...}}``. The
cases live in ``physgm.bench.verification`` (``analytic.all_cases``; the granular column
collapse at a = 0.5, 1, 2, 4 in ``granular``); ``--fast`` runs the coarse versions the default
tests use (8-20 cells across the column), the default the finer ones (20 cells across; the
column at a = 4 alone holds 12,800 particles for ~0.8 s of flow, most of the run's time).
"""

from __future__ import annotations

import argparse
import json
import time


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m physgm.bench sim-verify", description=__doc__)
    parser.add_argument("--fast", action="store_true", help="coarse versions (the default test tier)")
    args = parser.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    from physgm.bench.verification.analytic import all_cases

    cases, start = [], time.perf_counter()
    for case in all_cases(fast=args.fast):
        t0 = time.perf_counter()
        result = case()
        rows = result if isinstance(result, list) else [result]
        for row in rows:
            row["seconds"] = round((time.perf_counter() - t0) / len(rows), 2)
        cases.extend(rows)
    report = {
        "cases": cases,
        "summary": {
            "passed": sum(c["passed"] for c in cases),
            "total": len(cases),
            "fast": args.fast,
            "seconds": round(time.perf_counter() - start, 1),
        },
    }
    print(json.dumps(report))
    return report
