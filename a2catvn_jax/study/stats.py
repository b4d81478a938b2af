"""The statistics of an experiment's runs: pure functions of their logs and evaluations.

Means over seeds with Student's t-intervals (`t_interval`, `estimate`), Welch's t-test
(`welch_p`), Wilson's interval of a proportion over episodes pooled across seeds
(`wilson_interval`), the smoothed learning curves of a training log (`curves`), frames to
a success threshold, with the runs that never reach it censored at their last frame:
the Kaplan-Meier restricted mean (`restricted_mean`) and the log-rank test
(`logrank_p`); success by the start's distance from the goal (`success_by_distance`);
final training success and its late change, and `summarise`, which turns
the runs of an experiment (`RunRecord`s, read by the caller) into the summary every
report is made from. NumPy and SciPy only: nothing here reads or writes a file.
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
CONFIDENCE = 0.95  # of the t-intervals, Wilson's intervals and the restricted means' intervals
EVAL_POLICIES = ("sample", "greedy")  # the policies every run is evaluated with
DISTANCE_EDGES = (2.0, 4.0, 6.0, 8.0)  # metres: success by start distance in [0, 2), [2, 4), ... [8, inf)


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


def wilson_interval(successes: int, trials: int) -> tuple[float, float]:
    """Wilson's score interval (95%) of a proportion: `successes` of `trials` independent
    trials. (0, 1) when there is no trial."""
    if trials < 0 or not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials, got {successes} of {trials}")
    if trials == 0:
        return 0.0, 1.0
    z = stats.norm.ppf(0.5 + CONFIDENCE / 2)
    p, n = successes / trials, trials
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return float(max(0.0, centre - half)), float(min(1.0, centre + half))


def pooled_success(successes: Sequence[Optional[int]], episodes: Sequence[Optional[int]]) -> Optional[dict]:
    """Success over all episodes of the runs (None entries: runs not evaluated, left
    out): {"successes", "episodes", "rate", "low", "high"} with Wilson's 95% interval
    (episodes taken as independent, the spread between seeds left out); None without any."""
    pairs = [(int(k), int(n)) for k, n in zip(successes, episodes, strict=True) if k is not None and n is not None]
    k, n = sum(k for k, _ in pairs), sum(n for _, n in pairs)
    if n == 0:
        return None
    low, high = wilson_interval(k, n)
    return {"successes": k, "episodes": n, "runs": len(pairs), "rate": k / n, "low": low, "high": high}


def _censored(times, reached) -> tuple[np.ndarray, np.ndarray]:
    times, reached = np.asarray(times, float), np.asarray(reached, bool)
    if times.ndim != 1 or times.shape != reached.shape or times.size == 0:
        raise ValueError(f"need one time and one reached flag per run, got {times.shape} and {reached.shape}")
    if np.any(times < 0) or not np.all(np.isfinite(times)):
        raise ValueError(f"times must be finite and >= 0, got {times.tolist()}")
    return times, reached


def restricted_mean(times, reached, horizon: float) -> dict:
    """The restricted mean time to the event up to `horizon`: the area under the
    Kaplan-Meier curve of "not yet reached" from 0 to `horizon`, each run either reaching
    at `times[i]` (`reached[i]`) or censored there (never reached by its last frame).

    Returns {"mean", "low", "high", "se", "events", "runs", "horizon"}: the interval is
    the mean +- z * se, clipped to [0, horizon], with Greenwood's variance of the area,
    sum over event times t_j <= horizon of A_j^2 d_j / (n_j (n_j - d_j)) (A_j: the area
    from t_j to `horizon`; a term with n_j = d_j is 0, as in R's survRM2). The curve is
    `scipy.stats.ecdf`'s survival function of the censored data."""
    times, reached = _censored(times, reached)
    if not horizon > 0:
        raise ValueError(f"horizon must be > 0, got {horizon}")
    event_times = np.unique(times[reached & (times <= horizon)])
    if event_times.size:
        data = stats.CensoredData(uncensored=times[reached], right=times[~reached])
        survival = stats.ecdf(data).sf.evaluate(event_times)  # S just after each event time
    else:
        survival = np.zeros(0)
    # S is 1 up to the first event, then steps at each event time; integrate to the horizon.
    edges = np.concatenate([[0.0], event_times, [horizon]])
    heights = np.concatenate([[1.0], survival])
    areas = heights * np.diff(edges)  # areas[j + 1]: from event j to the next (or the horizon)
    mean = float(areas.sum())
    variance = 0.0
    for j, t in enumerate(event_times):
        at_risk = int(np.sum(times >= t))
        died = int(np.sum(reached & (times == t)))
        if at_risk > died:
            variance += areas[j + 1:].sum() ** 2 * died / (at_risk * (at_risk - died))
    se = math.sqrt(variance)
    z = stats.norm.ppf(0.5 + CONFIDENCE / 2)
    return {"mean": mean, "low": float(max(0.0, mean - z * se)), "high": float(min(horizon, mean + z * se)), "se": se,
            "events": int(np.sum(reached & (times <= horizon))), "runs": int(times.size),
            "horizon": float(horizon)}


def logrank_p(times_a, reached_a, times_b, reached_b) -> Optional[float]:
    """Two-sided p-value of the log-rank test between two sets of censored times
    (`scipy.stats.logrank`); None when it is undefined (no event in either)."""
    (ta, ra), (tb, rb) = _censored(times_a, reached_a), _censored(times_b, reached_b)
    if not (ra.any() or rb.any()):
        return None
    x = stats.CensoredData(uncensored=ta[ra], right=ta[~ra])
    y = stats.CensoredData(uncensored=tb[rb], right=tb[~rb])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        p = stats.logrank(x, y).pvalue
    return float(p) if math.isfinite(p) else None


def censored_frames(frames_to_threshold: Sequence[Optional[float]], frames_last: Sequence[float]):
    """(times, reached) of runs: the frame a run reaches the threshold, or its last frame
    (censored) when it never does."""
    times = [last if f is None else f for f, last in zip(frames_to_threshold, frames_last, strict=True)]
    return np.array(times, float), np.array([f is not None for f in frames_to_threshold], bool)


def _number(value) -> float:
    return math.nan if value is None else float(value)


def curves(rows: list[dict]) -> dict:
    """frames, and the smoothed success rate, episode length and SPL of a training log;
    "window": the rows each running mean is over (the first window - 1 rows average fewer)."""
    k = max(1, round(SMOOTH_FRACTION * len(rows)))
    frames = np.array([r["frames"] for r in rows], float)
    out = {"frames": frames, "window": k}
    for key in ("success_rate", "episode_length", "spl"):
        out[key] = smooth(np.array([_number(r.get(key)) for r in rows], float), k)
    return out


def frames_to_threshold(curve: dict, threshold: float) -> Optional[float]:
    """The first logged frame count at which the smoothed success rate, averaged over a
    full window of rows, reaches `threshold`. (The first rows of a run count only the
    few episodes that ended near their start, at the curriculum's easiest: a run logged
    often could otherwise "reach" the threshold at its first row.)"""
    full = np.arange(len(curve["frames"])) >= curve.get("window", 1) - 1
    hit = np.nonzero(full & (curve["success_rate"] >= threshold))[0]
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
    evals: dict  # policy -> houses -> its evaluation result there (None or absent: not evaluated)
    seconds: Optional[float]  # its training wall time, if recorded
    done: dict  # its done record: date, machine, git commit
    eval_log: tuple = ()  # the rows of its evaluations during training (train.eval), if it made any


def episode_successes(result: dict) -> int:
    """How many of an evaluation's episodes succeeded (its per-episode list, else its rate)."""
    per_episode = (result.get("per_episode") or {}).get("success")
    if per_episode is not None:
        return int(sum(bool(s) for s in per_episode))
    return int(round(result["success_rate"] * result["episodes"]))


def success_by_distance(results: Sequence[Optional[dict]]) -> Optional[dict]:
    """Success over the episodes of `results` pooled (None entries left out), in bands of
    the geodesic start-to-goal distance (`DISTANCE_EDGES`): {"edges", "successes",
    "episodes"}, one count per band; None when no result has per-episode distances."""
    success, distance = [], []
    for r in results:
        per_episode = (r or {}).get("per_episode") or {}
        if per_episode.get("start_distance") is not None and per_episode.get("success") is not None:
            success += [bool(s) for s in per_episode["success"]]
            distance += [float(d) for d in per_episode["start_distance"]]
    if not success:
        return None
    band = np.searchsorted(np.asarray(DISTANCE_EDGES), np.asarray(distance), side="right")
    bands = len(DISTANCE_EDGES) + 1
    return {"edges": list(DISTANCE_EDGES),
            "successes": np.bincount(band, weights=np.asarray(success, float), minlength=bands).astype(int).tolist(),
            "episodes": np.bincount(band, minlength=bands).tolist()}


def evaluation_entry(results: Sequence[Optional[dict]]) -> dict:
    """Per run (None: not evaluated): success rate, SPL, episodes, successes and the
    evaluation seed; "pooled", success over all their episodes (`pooled_success`); and
    "by_distance", that success by start distance (`success_by_distance`)."""
    def field(fn):
        return [None if r is None else fn(r) for r in results]

    entry = {"success_rate": field(lambda r: r["success_rate"]), "spl": field(lambda r: r["spl"]),
             "episodes": field(lambda r: int(r["episodes"])), "successes": field(episode_successes),
             "eval_seed": field(lambda r: r.get("seed"))}
    entry["pooled"] = pooled_success(entry["successes"], entry["episodes"])
    entry["by_distance"] = success_by_distance(results)
    return entry


HELD_OUT_CURVE = "held-out/sample/success_rate"  # what the held-out curve of `summarise` follows


def held_out_curve(eval_logs: Sequence[Sequence[dict]]) -> Optional[dict]:
    """Success in held-out houses (sampled) during training, over the runs that evaluated
    it: {"frames", "mean", "half_width_95", "runs"} at the frame counts every one of them
    evaluated at; None when no run did."""
    logs = [[r for r in rows if HELD_OUT_CURVE in r] for rows in eval_logs]
    logs = [rows for rows in logs if rows]
    if not logs:
        return None
    frames = sorted(set.intersection(*({float(r["frames"]) for r in rows} for rows in logs)))
    values = np.array([[next(float(r[HELD_OUT_CURVE]) for r in rows if float(r["frames"]) == f) for f in frames]
                       for rows in logs]).reshape(len(logs), len(frames))
    mean, half = t_interval(values)
    return {"frames": frames, "mean": mean.tolist(), "half_width_95": half.tolist(), "runs": len(logs)}


def summarise(exp: Experiment, records: Sequence[RunRecord], baseline: dict, threshold: float) -> dict:
    """Per variant of `exp`, from its runs' records: curves (mean and 95% t-band), frames
    to threshold (per run; the Kaplan-Meier restricted mean up to the shortest run's last
    frame, `rmst_horizon`, and the log-rank test against the first variant), final
    training success and evaluation numbers of each policy of `EVAL_POLICIES` ("eval":
    sampled, "eval_greedy"), each per seed, Welch's tests against the first variant, and
    ("held_out_curve") held-out success during training where runs evaluated it.
    `baseline`: policy -> houses -> result."""
    variants = {}
    horizon = min(float(r.log[-1]["frames"]) for r in records)
    first = None
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
        entry["frames_last"] = [float(c["frames"][-1]) for c in cs]
        # Welch's test counts a run that never reaches the threshold as reaching it at f_max.
        capped = [f_max if v is None else v for v in entry["frames_to_threshold"]]
        censored = censored_frames(entry["frames_to_threshold"], entry["frames_last"])
        entry["rmst_frames"] = restricted_mean(*censored, horizon)
        entry["final_success"] = [final_success(r.log) for r in mine]
        entry["late_change"] = [late_change(r.log) for r in mine]
        entry["training_seconds"] = [r.seconds for r in mine]
        entry["held_out_curve"] = held_out_curve([r.eval_log for r in mine])
        entry["eval"] = {h: evaluation_entry([(r.evals.get("sample") or {}).get(h) for r in mine])
                         for h in exp.evaluations}
        entry["eval_greedy"] = {h: evaluation_entry([(r.evals.get("greedy") or {}).get(h) for r in mine])
                                for h in exp.evaluations}
        if first is None:
            first = {"capped": capped, "censored": censored, "eval": entry["eval"], "eval_greedy": entry["eval_greedy"]}
            entry["welch_p_frames_vs_first"] = entry["logrank_p_frames_vs_first"] = None
            entry["welch_p_eval_success_vs_first"] = entry["welch_p_eval_greedy_success_vs_first"] = None
        else:
            entry["welch_p_frames_vs_first"] = welch_p(first["capped"], capped)
            entry["logrank_p_frames_vs_first"] = logrank_p(*first["censored"], *censored)
            for key, p_key in (("eval", "welch_p_eval_success_vs_first"),
                               ("eval_greedy", "welch_p_eval_greedy_success_vs_first")):
                entry[p_key] = {h: welch_p(*([v for v in e[h]["success_rate"] if v is not None]
                                             for e in (first[key], entry[key])))
                                for h in exp.evaluations}
        entry["trained"] = [{"date": r.done.get("date"), "machine": r.done.get("machine"), "git": r.done.get("git")}
                            for r in mine]
        variants[variant.label] = entry
    return {"experiment": exp.name, "title": exp.title, "threshold": threshold, "rmst_horizon": horizon,
            "variants": variants, "baselines": baseline}
