"""The statistics of an experiment's runs: pure functions of their logs and evaluations.

Means over seeds with Student's t-intervals (`t_interval`, `estimate`), Welch's t-test
(`welch_p`), the smoothed learning curves of a training log (`curves`), frames to a
success threshold, final training success and its late change, and `summarise`, which
turns the runs of an experiment (`RunRecord`s, read by the caller) into the summary
every report is made from. NumPy and SciPy only: nothing here reads or writes a file.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Callable, Optional, Sequence

import numpy as np
from scipy import stats

from a2catvn_jax.run.plots import smooth
from a2catvn_jax.study.registry import Experiment, Variant

SMOOTH_FRACTION = 0.1  # curves are running means over this fraction of a run's log rows
FINAL_FRACTION = 0.1  # "final" training success: the mean over this last fraction of the rows
CONFIDENCE = 0.95  # of the t-intervals


def standard_error(values: np.ndarray, axis: int = 0) -> np.ndarray:
    """Standard error of the mean over `axis` (0 for a single value)."""
    values = np.asarray(values, float)
    n = values.shape[axis]
    return values.std(axis=axis, ddof=1) / math.sqrt(n) if n > 1 else np.zeros_like(values.mean(axis=axis))


def t_interval(values: np.ndarray, axis: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Mean and 95% t-interval half-width over `axis` (half-width 0 for a single value)."""
    values = np.asarray(values, float)
    n = values.shape[axis]
    mean = values.mean(axis=axis)
    if n < 2:
        return mean, np.zeros_like(mean)
    return mean, stats.t.ppf(0.5 + CONFIDENCE / 2, n - 1) * standard_error(values, axis)


@dataclasses.dataclass(frozen=True)
class Estimate:
    """A mean over runs and its 95% t-interval (None with fewer than two values)."""

    mean: float
    low: Optional[float]
    high: Optional[float]
    n: int

    def format(self, fmt: Callable[[float], str] = "{:.2f}".format) -> str:
        if self.low is None:
            return fmt(self.mean)
        return f"{fmt(self.mean)} [{fmt(self.low)}, {fmt(self.high)}]"


def estimate(values, lo: float = -math.inf, hi: float = math.inf) -> Optional[Estimate]:
    """The `Estimate` of the finite values among `values` (None and NaN left out), the
    interval clipped to [lo, hi]; None when there is no value."""
    xs = np.array([v for v in values if v is not None and math.isfinite(v)], float)
    if xs.size == 0:
        return None
    mean, half = t_interval(xs)
    if xs.size < 2:
        return Estimate(float(mean), None, None, 1)
    return Estimate(float(mean), float(max(lo, mean - half)), float(min(hi, mean + half)), int(xs.size))


def welch_p(a, b) -> Optional[float]:
    """Two-sided p-value of Welch's t-test between two samples (None when it is undefined)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.size < 2 or b.size < 2 or (np.ptp(a) == 0 and np.ptp(b) == 0):
        return None
    with warnings.catch_warnings():  # one sample of equal values (never reached: all f_max) is a valid case
        warnings.simplefilter("ignore", RuntimeWarning)
        p = stats.ttest_ind(a, b, equal_var=False).pvalue
    return float(p) if math.isfinite(p) else None


def _number(value) -> float:
    return math.nan if value is None else float(value)


def curves(rows: list[dict]) -> dict:
    """frames, and the smoothed success rate, episode length and SPL of a training log."""
    k = max(1, round(SMOOTH_FRACTION * len(rows)))
    frames = np.array([r["frames"] for r in rows], float)
    out = {"frames": frames}
    for key in ("success_rate", "episode_length", "spl"):
        out[key] = smooth(np.array([_number(r.get(key)) for r in rows], float), k)
    return out


def frames_to_threshold(curve: dict, threshold: float) -> Optional[float]:
    """The first logged frame count at which the smoothed success rate reaches `threshold`."""
    hit = np.nonzero(curve["success_rate"] >= threshold)[0]
    return float(curve["frames"][hit[0]]) if hit.size else None


def _mean_success(rows: list[dict]) -> float:
    values = [r["success_rate"] for r in rows if r.get("success_rate") is not None and math.isfinite(r["success_rate"])]
    return float(np.mean(values)) if values else math.nan


def _final_count(rows: list[dict]) -> int:
    """How many rows make the last FINAL_FRACTION of a training log (at least one)."""
    return max(1, round(FINAL_FRACTION * len(rows)))


def final_success(rows: list[dict]) -> float:
    """The mean training success rate over the last FINAL_FRACTION of a training log."""
    return _mean_success(rows[-_final_count(rows):])


def late_change(rows: list[dict]) -> float:
    """The training success rate's change at the end of a log: the mean over its last
    FINAL_FRACTION of rows minus the mean over the FINAL_FRACTION before those. Above 0:
    the run was still improving when it ended."""
    k = _final_count(rows)
    if len(rows) < 2 * k:
        return math.nan
    return _mean_success(rows[-k:]) - _mean_success(rows[-2 * k:-k])


@dataclasses.dataclass(frozen=True)
class RunRecord:
    """What the statistics use of one finished run (read from the store by the caller)."""

    variant: Variant
    seed: int
    relative: str  # SCALE/CONFIG/RUN_KEY/seed_N, where the run is stored
    log: list[dict]  # its stored training log
    evals: dict  # houses -> its evaluation result there (None: not evaluated)
    seconds: Optional[float]  # its training wall time, if recorded
    done: dict  # its done record: date, machine, git commit


def summarise(exp: Experiment, records: Sequence[RunRecord], baseline: dict, threshold: float) -> dict:
    """Per variant of `exp`, from its runs' records: curves (mean and 95% t-band), frames
    to threshold, final training success and evaluation numbers, each per seed, and
    Welch's tests against the first variant. `baseline`: policy -> houses -> result."""
    variants = {}
    first_frames = first_eval = None
    for variant in exp.variants:
        mine = [r for r in records if r.variant == variant]
        cs = [curves(r.log) for r in mine]
        n = min(len(c["frames"]) for c in cs)
        f_max = max(float(c["frames"][-1]) for c in cs)
        entry = {"seeds": [r.seed for r in mine], "runs": [r.relative for r in mine],
                 "frames": cs[0]["frames"][:n].tolist()}
        for key in ("success_rate", "episode_length"):
            stacked = np.stack([c[key][:n] for c in cs])
            mean, half = t_interval(stacked)
            entry[key] = {"mean": mean.tolist(), "sem": standard_error(stacked).tolist(),
                          "half_width_95": half.tolist()}
        entry["frames_to_threshold"] = [frames_to_threshold(c, threshold) for c in cs]
        entry["frames_max"] = f_max
        # Welch's test counts a run that never reaches the threshold as reaching it at f_max.
        capped = [f_max if v is None else v for v in entry["frames_to_threshold"]]
        if first_frames is None:
            first_frames = capped
        entry["welch_p_frames_vs_first"] = None if variant == exp.variants[0] else welch_p(first_frames, capped)
        entry["final_success"] = [final_success(r.log) for r in mine]
        entry["late_change"] = [late_change(r.log) for r in mine]
        entry["training_seconds"] = [r.seconds for r in mine]
        entry["eval"] = {h: {m: [None if r.evals[h] is None else r.evals[h][m] for r in mine]
                             for m in ("success_rate", "spl")} for h in exp.evaluations}
        if first_eval is None:
            first_eval = entry["eval"]
        entry["welch_p_eval_success_vs_first"] = None if variant == exp.variants[0] else {
            h: welch_p(*([v for v in e[h]["success_rate"] if v is not None] for e in (first_eval, entry["eval"])))
            for h in exp.evaluations}
        entry["trained"] = [{"date": r.done.get("date"), "machine": r.done.get("machine"), "git": r.done.get("git")}
                            for r in mine]
        variants[variant.label] = entry
    return {"experiment": exp.name, "title": exp.title, "threshold": threshold, "variants": variants,
            "baselines": baseline}
