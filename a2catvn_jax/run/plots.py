"""Learning curves from the metrics.jsonl of training runs.

One panel per metric (success rate, episode length, SPL by default) against frames,
one line per run, each smoothed by a running mean over `--smooth` log rows.
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


def plot_runs(workdirs, out, metrics=METRICS, window: int = 5, labels=None, title=None, log_y: bool = False):
    """Write a PNG of `metrics` against frames for each run directory (`log_y`: logarithmic y axes)."""
    fig = Figure(figsize=(4.2 * len(metrics), 3.2))
    axes = fig.subplots(1, len(metrics), squeeze=False)
    for i, workdir in enumerate(workdirs):
        rows = read_jsonl(Path(workdir) / "metrics.jsonl")
        frames = np.array([r["frames"] for r in rows], float)
        label = labels[i] if labels else Path(workdir).name
        for ax, key in zip(axes[0], metrics):
            y = np.array([r.get(key, np.nan) for r in rows], float)
            ax.plot(frames, smooth(y, window), label=label)
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
