"""``python -m physgm.view RUN_DIR``: the simulated Gaussians of a run folder, over time, in the browser."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m physgm.view",
        description="Serve a simulate.py run folder's moving Gaussians (gaussians_t.npz) in the browser: "
        "time slider, play/pause, free camera.",
    )
    parser.add_argument("run_dir", help="a run folder written by simulate.py, or a gaussians_t*.npz file")
    parser.add_argument("--run", default="mean", help="which future: mean (default) or sample0, sample1, ...")
    parser.add_argument(
        "--host", default="127.0.0.1", help="address to listen on (0.0.0.0: the whole network)"
    )
    parser.add_argument(
        "--port",
        type=int,
        default=None,
        help="port (default 8080, the next free one if taken; --screenshot: any free one)",
    )
    parser.add_argument("--frame", type=int, default=0, help="frame shown first")
    parser.add_argument("--paused", action="store_true", help="start paused instead of playing")
    parser.add_argument(
        "--screenshot",
        metavar="PNG",
        help="instead of serving: save the viewer at --frame as seen in "
        "headless "
        "Chromium (needs chromium installed) and exit",
    )
    parser.add_argument(
        "--size", type=int, nargs=2, default=(960, 540), metavar=("W", "H"), help="--screenshot size, px"
    )
    args = parser.parse_args(argv)
    try:
        from physgm.view.server import save_screenshot, serve

        if args.screenshot:
            out = save_screenshot(
                args.run_dir, args.screenshot, args.run, args.frame, *args.size, port=args.port or 0
            )
            print(out)
        else:
            serve(args.run_dir, args.run, args.host, args.port or 8080, args.frame, not args.paused)
    except (ImportError, FileNotFoundError, ValueError, TimeoutError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
