"""Training metrics: summed over a logging interval, written as JSON lines, CSV and TensorBoard.

`Interval` accumulates the per-update metrics of the training update (loss terms are
averaged; episode counts and sums are added) and turns them into one row with the
episode statistics of the interval: success rate, mean episode length, return and SPL.
`MetricsWriter` appends rows to `metrics.jsonl` and `metrics.csv` in the work
directory and to TensorBoard event files in `tb/`, each row written and flushed before
`write` returns; a write that fails (a full disk included) is taken back from the files
and raises `MetricsWriteError`, one line saying what and where. `truncate_metrics` drops
the rows after an update (a run resumed from an earlier checkpoint), so that the files
hold each update once.
"""

from __future__ import annotations

import csv
import json
import math
import os
import socket
import struct
import time
import uuid
from pathlib import Path
from typing import Callable, Optional

import numpy as np
from tensorboardX.proto.event_pb2 import Event, SessionLog
from tensorboardX.record_writer import masked_crc32c
from tensorboardX.summary import scalar

from a2catvn_jax.agent.acting import EPISODE_STATS
from a2catvn_jax.errors import UserError


class MetricsWriteError(UserError, RuntimeError):
    """A metrics file (JSON lines, CSV or TensorBoard) could not be written."""


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
    """Appends metric rows to <name>.jsonl, <name>.csv and TensorBoard in `workdir`.

    `note()` (optional) is added to the message of a failed write (e.g. which checkpoint
    is the last complete one); `purge_step`: TensorBoard hides the events of earlier
    event files from this step (frames) on, those of a run resumed from an earlier point."""

    def __init__(self, workdir: str | os.PathLike, tensorboard: bool = True, name: str = "metrics",
                 note: Optional[Callable[[], str]] = None, purge_step: Optional[int] = None):
        self.workdir = Path(workdir)
        self.note = note
        self.failed = False
        self.jsonl_path = self.workdir / f"{name}.jsonl"
        self.csv_path = self.workdir / f"{name}.csv"
        self.tb = None
        self._csv_fields = None
        with self._failing("open", self.workdir):
            self.workdir.mkdir(parents=True, exist_ok=True)
            self.jsonl_path.touch()
            if self.csv_path.exists() and self.csv_path.stat().st_size:
                with open(self.csv_path, encoding="utf-8") as fh:
                    self._csv_fields = next(csv.reader(fh), None)
            self.tb = _EventFile(self.workdir / "tb", purge_step) if tensorboard else None

    def write(self, row: dict):
        """Append `row` to every file; `MetricsWriteError` (and none of it kept) if one fails."""
        row = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in row.items()}
        sizes = {p: p.stat().st_size if p.exists() else 0 for p in (self.jsonl_path, self.csv_path)}
        if self.tb is not None:
            sizes[self.tb.path] = self.tb.size()
        try:
            with self._failing(f"write the metrics of update {row.get('update', row.get('epoch', '?'))} to",
                               self.jsonl_path):
                with open(self.jsonl_path, "a", encoding="utf-8") as fh:  # closed (and its buffer gone) even if it fails
                    fh.write(json.dumps(row, allow_nan=True) + "\n")
            with self._failing("write the metrics to", self.csv_path):
                self._write_csv(row)
            if self.tb is not None:
                with self._failing("write the TensorBoard events to", self.tb.path):
                    self.tb.scalars(row, int(row.get("frames", 0)))
        except MetricsWriteError:
            for path, size in sizes.items():  # take the row back from the files that got it
                try:
                    os.truncate(path, size)
                except OSError:
                    pass
            raise

    def _write_csv(self, row: dict):
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

    def _failing(self, what: str, where):
        return _Failing(self, what, where)

    def close(self):
        """Nothing stays open between rows; kept for the writers' callers."""

    def _message(self, what: str, where, e: OSError) -> str:
        reason = (e.strerror or str(e)) + (" (the disk is full)" if e.errno == 28 else "")
        note = self.note() if self.note is not None else ""
        return f"cannot {what} {where}: {reason}" + (f"; {note}" if note else "")


class _Failing:
    """A block whose OSError becomes a `MetricsWriteError` of its writer."""

    def __init__(self, writer: MetricsWriter, what: str, where):
        self.writer, self.what, self.where = writer, what, where

    def __enter__(self):
        return self

    def __exit__(self, kind, e, tb):
        if isinstance(e, OSError):
            self.writer.failed = True
            raise MetricsWriteError(self.writer._message(self.what, self.where, e)) from None
        return False


class _EventFile:
    """A TensorBoard event file whose scalars are written, flushed and synced in the
    caller's thread, one row at a time (tensorboardX's `SummaryWriter` writes from a
    thread of its own: there a failed write is lost, and the writes after it wait forever
    for the dead thread). The records are TensorBoard's: length, CRCs, an `Event`."""

    def __init__(self, logdir: Path, purge_step: Optional[int] = None):
        logdir.mkdir(parents=True, exist_ok=True)
        # A name of its own: a run and its resumption in one second would otherwise share one.
        self.path = logdir / f"events.out.tfevents.{int(time.time()):010d}.{socket.gethostname()}.{uuid.uuid4().hex[:8]}"
        now = time.time()
        first = [Event(wall_time=now, file_version="brain.Event:2")]
        if purge_step is not None:  # TensorBoard hides earlier files' events from this step on
            first = [Event(wall_time=now, step=purge_step, file_version="brain.Event:2"),
                     Event(wall_time=now, step=purge_step, session_log=SessionLog(status=SessionLog.START))]
        self._append(first)

    def size(self) -> int:
        return self.path.stat().st_size if self.path.exists() else 0

    def scalars(self, row: dict, step: int) -> None:
        now = time.time()
        self._append([Event(wall_time=now, step=step, summary=scalar(k, v)) for k, v in row.items()
                      if k != "frames" and isinstance(v, (int, float)) and math.isfinite(v)])

    def _append(self, events) -> None:
        data = bytearray()
        for event in events:
            body = event.SerializeToString()
            header = struct.pack("Q", len(body))
            data += header + struct.pack("I", masked_crc32c(header)) + body + struct.pack("I", masked_crc32c(body))
        with open(self.path, "ab") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())


def truncate_metrics(workdir: str | os.PathLike, update: int, name: str = "metrics", key: str = "update") -> int:
    """Drop the rows of <name>.jsonl and <name>.csv in `workdir` whose `key` is above
    `update` (and JSON lines that cannot be read: a write cut short); returns how many
    JSON lines were dropped. A run resumed from update `update` writes those rows again."""
    workdir = Path(workdir)
    try:
        return _truncate(workdir, update, name, key)
    except OSError as e:
        reason = (e.strerror or str(e)) + (" (the disk is full)" if e.errno == 28 else "")
        raise MetricsWriteError(f"cannot remove the rows after {key} {update} from {workdir / name}.jsonl/.csv: "
                                f"{reason}") from None


def _truncate(workdir: Path, update: int, name: str, key: str) -> int:
    jsonl, csv_path = workdir / f"{name}.jsonl", workdir / f"{name}.csv"
    dropped = 0
    if jsonl.exists():
        kept = []
        for line in jsonl.read_text(encoding="utf-8").splitlines():
            try:
                row = json.loads(line)
            except ValueError:
                dropped += bool(line.strip())
                continue
            if isinstance(row, dict) and isinstance(row.get(key), (int, float)) and row[key] <= update:
                kept.append(line)
            else:
                dropped += 1
        if dropped:
            _replace(jsonl, "".join(line + "\n" for line in kept))
    if csv_path.exists() and csv_path.stat().st_size:
        with open(csv_path, newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
        header, body = rows[0], rows[1:]
        column = header.index(key) if key in header else None

        def keep(r):
            try:
                return column is not None and len(r) == len(header) and float(r[column]) <= update
            except ValueError:
                return False

        kept_rows = [r for r in body if keep(r)]
        if len(kept_rows) != len(body):
            with open(csv_path.with_suffix(".csv.tmp"), "w", newline="", encoding="utf-8") as fh:
                csv.writer(fh).writerows([header] + kept_rows)
            os.replace(csv_path.with_suffix(".csv.tmp"), csv_path)
    return dropped


def _replace(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def read_jsonl(path: str | os.PathLike) -> list[dict]:
    with open(path, encoding="utf-8") as fh:
        return [json.loads(line) for line in fh if line.strip()]
