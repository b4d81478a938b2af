"""Learning curves from the metrics.jsonl of training runs.

One panel per metric (success rate, episode length, SPL by default) against frames,
one line per run, each smoothed by a running mean over `--smooth` log rows. A metric
of the evaluations during training (eval.jsonl, `train.eval`: e.g.
"held-out/sample/success_rate") is drawn as measured, a point per evaluation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from a2catvn_jax.run.logger import read_jsonl

METRICS = ("success_rate", "episode_length", "spl")
LABELS = {"success_rate": "success rate", "episode_length": "episode length", "spl": "SPL",
          "episode_return": "episode return", "loss/total": "total loss"}


def smooth(y: np.ndarray, k: int) -> np.ndarray:
    """Running mean over the last k finite values (NaN rows are skipped)."""
    out = np.full_like(y, np.nan)
    for i in range(len(y)):
        window = y[max(0, i - k + 1) : i + 1]
        window = window[np.isfinite(window)]
        if window.size:
            out[i] = window.mean()
    return out


LOGS = ("metrics", "eval")  # a run's logs: training rows, then evaluations during training


def logged(workdir) -> dict:
    """{log name: its rows} of the logs in a run directory (eval only where the run has one)."""
    return {name: read_jsonl(Path(workdir) / f"{name}.jsonl") for name in LOGS
            if name == "metrics" or (Path(workdir) / f"{name}.jsonl").exists()}


def plot_runs(workdirs, out, metrics=METRICS, window: int = 5, labels=None, title=None, log_y: bool = False) -> Figure:
    """Write a PNG of `metrics` against frames for each run directory (`log_y`: logarithmic
    y axes); returns the figure."""
    fig = Figure(figsize=(4.2 * len(metrics), 3.2))
    axes = fig.subplots(1, len(metrics), squeeze=False)
    for i, workdir in enumerate(workdirs):
        logs = logged(workdir)
        label = labels[i] if labels else Path(workdir).name
        for ax, key in zip(axes[0], metrics):
            name = next((n for n, rows in logs.items() if any(key in r for r in rows)), "metrics")
            rows = logs[name]
            frames = np.array([r["frames"] for r in rows], float)
            y = np.array([r.get(key, np.nan) for r in rows], float)
            if name == "metrics":
                ax.plot(frames, smooth(y, window), label=label)
            else:
                ax.plot(frames, y, marker="o", label=label)
    for ax, key in zip(axes[0], metrics):
        ax.set_xlabel("frames")
        ax.set_title(LABELS.get(key, key))
        ax.grid(alpha=0.3)
        if log_y:
            ax.set_yscale("log")
    if len(workdirs) > 1:
        axes[0][0].legend()
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    return fig
