"""Learning curves from the metrics.jsonl of training runs.

    python -m a2catvn_jax.plots RUN_DIR [RUN_DIR ...] --out curve.png [--smooth 5]

One panel per metric (success rate, episode length, SPL by default) against frames,
one line per run, each smoothed by a running mean over `--smooth` log rows.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from a2catvn_jax.run.plots import METRICS, plot_runs


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m a2catvn_jax.plots", description=__doc__.split("\n\n")[0])
    parser.add_argument("workdirs", nargs="+")
    parser.add_argument("--out", required=True, help="PNG file")
    parser.add_argument("--metrics", nargs="+", default=list(METRICS))
    parser.add_argument("--smooth", type=int, default=5, help="running mean over this many log rows")
    parser.add_argument("--title", default=None)
    args = parser.parse_args(argv)
    for w in args.workdirs:
        if not (Path(w) / "metrics.jsonl").exists():
            parser.error(f"{w}: no metrics.jsonl")
    plot_runs(args.workdirs, args.out, args.metrics, args.smooth, title=args.title)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
