"""Training metrics: summed over a logging interval, written as JSON lines, CSV and TensorBoard.

`Interval` accumulates the per-update metrics of the training update (loss terms are
averaged; episode counts and sums are added) and turns them into one row with the
episode statistics of the interval: success rate, mean episode length, return and SPL.
`MetricsWriter` appends rows to `metrics.jsonl` and `metrics.csv` in the work
directory and to TensorBoard event files in `tb/`.
"""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

import numpy as np
from tensorboardX import SummaryWriter

from a2catvn_jax.agent.acting import EPISODE_STATS


class Interval:
    """Per-update metrics accumulated between two log lines."""

    def __init__(self):
        self.reset()

    def reset(self):
        self.sums: dict[str, float] = {}
        self.updates = 0

    def add(self, metrics: dict, updates: int = 1):
        """Add one update's metrics, or the sums of `updates` updates' metrics."""
        for k, v in metrics.items():
            self.sums[k] = self.sums.get(k, 0.0) + float(v)
        self.updates += updates

    def row(self) -> dict:
        """Means of the loss terms and the episode statistics of the interval."""
        n = max(self.updates, 1)
        row = {k: v / n for k, v in self.sums.items() if k not in EPISODE_STATS}
        episodes = self.sums.get("episodes", 0.0)
        row["episodes"] = int(episodes)
        for name, total in (("success_rate", "successes"), ("episode_length", "length_sum"),
                            ("spl", "spl_sum"), ("episode_return", "return_sum")):
            row[name] = self.sums.get(total, 0.0) / episodes if episodes else math.nan
        return row


class MetricsWriter:
    """Appends metric rows to <name>.jsonl, <name>.csv and TensorBoard in `workdir`."""

    def __init__(self, workdir: str | os.PathLike, tensorboard: bool = True, name: str = "metrics"):
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.jsonl = open(self.workdir / f"{name}.jsonl", "a", encoding="utf-8")
        self.csv_path = self.workdir / f"{name}.csv"
        self._csv_fields = None
        if self.csv_path.exists() and self.csv_path.stat().st_size:
            with open(self.csv_path, encoding="utf-8") as fh:
                self._csv_fields = next(csv.reader(fh), None)
        self.tb = SummaryWriter(str(self.workdir / "tb")) if tensorboard else None

    def write(self, row: dict):
        row = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in row.items()}
        self.jsonl.write(json.dumps(row, allow_nan=True) + "\n")
        self.jsonl.flush()
        if self._csv_fields is None:
            self._csv_fields = list(row)
            with open(self.csv_path, "w", newline="", encoding="utf-8") as fh:
                csv.writer(fh).writerow(self._csv_fields)
        elif any(k not in self._csv_fields for k in row):  # a column appears (e.g. a periodic diagnostic)
            with open(self.csv_path, newline="", encoding="utf-8") as fh:
                old = list(csv.DictReader(fh))
            self._csv_fields += [k for k in row if k not in self._csv_fields]
            with open(self.csv_path, "w", newline="", encoding="utf-8") as fh:
                writer = csv.DictWriter(fh, self._csv_fields, restval="")
                writer.writeheader()
                writer.writerows(old)
        with open(self.csv_path, "a", newline="", encoding="utf-8") as fh:
            csv.writer(fh).writerow([row.get(k, "") for k in self._csv_fields])
        if self.tb is not None:
            step = int(row.get("frames", 0))
            for k, v in row.items():
                if k != "frames" and isinstance(v, (int, float)) and math.isfinite(v):
                    self.tb.add_scalar(k, v, step)
            self.tb.flush()

    def close(self):
        self.jsonl.close()
        if self.tb is not None:
            self.tb.close()


def read_jsonl(path: str | os.PathLike) -> list[dict]:
    with open(path, encoding="utf-8") as fh:
        return [json.loads(line) for line in fh if line.strip()]
