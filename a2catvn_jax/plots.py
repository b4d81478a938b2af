"""Learning curves from the metrics.jsonl of training runs.

    python -m a2catvn_jax.plots RUN_DIR [RUN_DIR ...] --out curve.png [--smooth 5] [--metrics KEY ...] [--log-y]

One panel per metric (success rate, episode length, SPL by default) against frames,
one line per run, each smoothed by a running mean over `--smooth` log rows. Any column
of the runs' metrics.jsonl is a metric: e.g. `--metrics grad_norm/reward_prediction
grad_norm/actor --log-y` for the gradient norms a run with `train.grad_norm_every`
logs, and so is any column of eval.jsonl (evaluation during training, `train.eval`),
e.g. `--metrics held-out/sample/success_rate held-out/sample/spl`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from a2catvn_jax.run.plots import METRICS, logged, plot_runs


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m a2catvn_jax.plots", description=__doc__.split("\n\n")[0])
    parser.add_argument("workdirs", nargs="+")
    parser.add_argument("--out", required=True, help="PNG file")
    parser.add_argument("--metrics", nargs="+", default=list(METRICS))
    parser.add_argument("--smooth", type=int, default=5, help="running mean over this many log rows")
    parser.add_argument("--title", default=None)
    parser.add_argument("--log-y", action="store_true", help="logarithmic y axes")
    args = parser.parse_args(argv)
    if args.smooth < 1:
        parser.error(f"--smooth must be >= 1, got {args.smooth}")
    columns = set()
    for w in args.workdirs:
        if not (Path(w) / "metrics.jsonl").exists():
            parser.error(f"{w}: no metrics.jsonl")
        columns.update(k for rows in logged(w).values() for row in rows for k in row)
    unknown = [m for m in args.metrics if m not in columns]
    if unknown:
        parser.error(f"no run logs {', '.join(map(repr, unknown))}; the runs' columns: {', '.join(sorted(columns))}")
    plot_runs(args.workdirs, args.out, args.metrics, args.smooth, title=args.title, log_y=args.log_y)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
