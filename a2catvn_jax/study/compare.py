"""Variants of different experiments side by side, from their stored summaries.

An experiment's report tests each variant against its own first variant only. A
comparison across experiments (the same agent at two gradient-norm clips, each in its
own experiment; a variant against another experiment's control) reads what the
reports already stored: `STORE/SCALE/EXPERIMENT.json` (written by `run_experiment`,
with every number per seed) and, for the gradient norms, the `metrics.jsonl` and
`config.yaml` of each run it lists. Nothing is trained or evaluated, and the numbers
are the reports' own (their threshold, their evaluation episodes).

    python -m a2catvn_jax.experiments --compare "aux:A2C+UNREAL" "aux_clip40:A2C+UNREAL, clip 40"

Every variant after the first is tested against the first with Welch's t-test (frames
to threshold with a run that never reaches it counted at its last frame, as in the
reports; final training success; evaluation success in each house set).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from a2catvn_jax.errors import UserError
from a2catvn_jax.run.checkpoint import CheckpointError, read_run_config
from a2catvn_jax.study.registry import EVAL_SETS, EXPERIMENTS
from a2catvn_jax.study.formats import format_estimate, format_frames, frames_text, seeds_text
from a2catvn_jax.study.stats import welch_p
from a2catvn_jax.study.store import DEFAULT_STORE

VARIANT_KEYS = ("seeds", "runs", "frames_to_threshold", "frames_max", "final_success", "eval")


class CompareError(UserError):
    """A comparison that cannot be made: a malformed VARIANT, a summary or a run not stored."""


def _parse(spec: str) -> tuple[str, str]:
    name, sep, label = spec.partition(":")
    if not sep or not name or not label:
        raise CompareError(f"{spec!r}: name a variant as EXPERIMENT:LABEL, e.g. 'aux:A2C+UNREAL'")
    return name, label


def _read_summary(path: Path) -> dict:
    """An experiment summary, checked for what a comparison reads."""
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise CompareError(f"{path} cannot be read as an experiment summary: {err}") from None
    problem = None
    if not isinstance(summary, dict) or not isinstance(summary.get("variants"), dict):
        problem = "no 'variants' mapping"
    elif not isinstance(summary.get("threshold"), (int, float)):
        problem = "no numeric 'threshold'"
    else:
        for label, entry in summary["variants"].items():
            missing = [k for k in VARIANT_KEYS if not isinstance(entry, dict) or k not in entry]
            if missing:
                problem = f"variant {label!r} lacks {', '.join(missing)}"
                break
    if problem:
        raise CompareError(f"{path} is not an experiment summary as the runner writes it: {problem}")
    return summary


def load_variants(specs: Sequence[str], scale: str = "cpu", store=DEFAULT_STORE) -> list[dict]:
    """The stored summary entry of each `EXPERIMENT:LABEL` in `specs`, with "experiment",
    "label", "threshold" and "episodes" (the evaluation episodes its numbers rest on,
    "episodes_used", where the summary records them; else those asked for) added. Raises `CompareError` naming what is
    missing, and when the reports' success thresholds differ."""
    if len(specs) < 2:
        raise CompareError(f"compare needs at least two variants, got {len(specs)}")
    store = Path(store)
    summaries, out = {}, []
    for spec in specs:
        name, label = _parse(spec)
        if name not in summaries:
            path = store / scale / f"{name}.json"
            if not path.is_file():
                hint = (f"report it first: python -m a2catvn_jax.experiments {name} --stored-seeds --no-evaluate "
                        f"--scale {scale}"
                        + ("" if store == Path(DEFAULT_STORE) else f" --store {store}")
                        if name in EXPERIMENTS else "experiments: " + ", ".join(EXPERIMENTS))
                raise CompareError(f"no stored summary of {name!r} at {scale} scale ({path}); {hint}")
            summaries[name] = _read_summary(path)
        summary = summaries[name]
        if label not in summary["variants"]:
            raise CompareError(f"{name} has no reported variant {label!r}; its variants: "
                               + ", ".join(map(repr, summary["variants"])))
        used = summary.get("episodes_used")  # what the numbers rest on, where the runner recorded it
        episodes = summary.get("episodes") if not used else used[0] if len(used) == 1 else " or ".join(map(str, used))
        out.append({**summary["variants"][label], "experiment": name, "label": label,
                    "threshold": summary["threshold"], "episodes": episodes})
    if len({v["threshold"] for v in out}) > 1:
        raise CompareError("the variants' reports use different success thresholds ("
                           + ", ".join(f"{v['experiment']}: {v['threshold']:g}" for v in out)
                           + "): their frames to threshold cannot be compared")
    return out


def gradient_norms(variant: dict, store=DEFAULT_STORE) -> list[Optional[dict]]:
    """Per run of `variant` (None for a run whose log has no gradient norm): the median,
    smallest and largest logged gradient norm, how many log rows exceed the run's clip
    (`train.max_grad_norm` of its stored configuration, read as training reads an older
    run's), how many rows there are and `train.log_every`. The norm is the whole
    update's before clipping, and each log row holds its mean over the row's
    `log_every` updates."""
    runs = []
    for rel in variant["runs"]:
        directory = Path(store) / rel
        try:
            rows = [json.loads(line) for line in (directory / "metrics.jsonl").read_text().splitlines() if line]
            norms = np.array([r["grad_norm"] for r in rows if r.get("grad_norm") is not None], float)
            cfg = read_run_config(directory)
        except (OSError, ValueError, TypeError, AttributeError, CheckpointError) as err:
            raise CompareError(f"stored run {directory} cannot be read: {err}") from None
        clip = float(cfg.train.max_grad_norm)
        runs.append(None if norms.size == 0 else {
            "median": float(np.median(norms)), "min": float(norms.min()), "max": float(norms.max()), "clip": clip,
            "above": int((norms > clip).sum()), "rows": int(norms.size), "log_every": int(cfg.train.log_every)})
    return runs


def _range(values: Sequence[float]) -> str:
    low, high = f"{min(values):.2f}", f"{max(values):.2f}"
    return low if low == high else f"{low}–{high}"


def _norm_cells(per_run: list[Optional[dict]]) -> list[str]:
    runs = [r for r in per_run if r is not None]
    if not runs:
        return ["–", "–"]
    missing = "" if len(runs) == len(per_run) else f" ({len(runs)} of {len(per_run)} runs log it)"
    clips = ", ".join(f"{c:g}" for c in sorted({r["clip"] for r in runs}))
    return [f"{_range([r['median'] for r in runs])}; {_range([r['min'] for r in runs] + [r['max'] for r in runs])}"
            + missing,
            f"{sum(r['above'] for r in runs)}/{sum(r['rows'] for r in runs)} (clip {clips})"]


def _capped(variant: dict) -> list[float]:
    return [variant["frames_max"] if f is None else f for f in variant["frames_to_threshold"]]


def _present(values) -> list[float]:
    return [v for v in values if v is not None and math.isfinite(v)]


def _p_text(p: Optional[float]) -> str:
    return "–" if p is None else f"{p:.2g}"


def _differences(variants: list[dict]) -> list[str]:
    """Notes on what differs between the reports beyond the variants themselves."""
    notes = []
    lengths = {v["frames_max"] for v in variants}
    if len(lengths) > 1:
        notes.append("The runs differ in length (" + ", ".join(f"{v['label']} ({v['experiment']}) "
                                                             f"{frames_text(v['frames_max'])}" for v in variants)
                     + " frames): final training success and the count at which a run that never reaches the "
                       "threshold enters Welch's test are not like for like.")
    episodes = {v["episodes"] for v in variants}
    if len(episodes) > 1:
        notes.append("The reports evaluate each run over different numbers of episodes ("
                     + ", ".join(f"{v['experiment']}: {v['episodes']}" for v in variants) + ").")
    return notes


def compare(specs: Sequence[str], scale: str = "cpu", store=DEFAULT_STORE) -> str:
    """A markdown table of the variants `specs` (`EXPERIMENT:LABEL`, from the stored
    summaries at `scale`), a table of Welch's p-values of each against the first, and
    notes on what the numbers are."""
    variants = load_variants(specs, scale, store)
    houses = [h for h in EVAL_SETS if any(h in v["eval"] for v in variants)]
    threshold = variants[0]["threshold"]
    norms = [gradient_norms(v, store) for v in variants]
    head = ["variant", "experiment", "seeds", f"frames to success {threshold:g}", "final training success",
            *(f"success, {EVAL_SETS[h]}" for h in houses),
            "gradient norm: the runs' medians; all rows", "log rows above the clip"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for v, per_run in zip(variants, norms):
        cells = [v["label"], v["experiment"], seeds_text(v["seeds"]),
                 format_frames(v["frames_to_threshold"], v["frames_max"]), format_estimate(v["final_success"])]
        cells += [format_estimate(v["eval"][h]["success_rate"]) if h in v["eval"] else "–" for h in houses]
        cells += _norm_cells(per_run)
        lines.append("| " + " | ".join(cells) + " |")
    first, others = variants[0], variants[1:]
    tests = [(f"frames to {threshold:g}", _capped), ("final training success", lambda v: _present(v["final_success"]))]
    tests += [(f"success, {EVAL_SETS[h]}", lambda v, h=h: _present(v["eval"][h]["success_rate"]))
              for h in houses if all(h in v["eval"] for v in variants)]
    head = [f"Welch's p against {first['label']} ({first['experiment']})", *(what for what, _ in tests)]
    lines += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for v in others:
        cells = [f"{v['label']} ({v['experiment']})", *(_p_text(welch_p(values(first), values(v)))
                                                         for _, values in tests)]
        lines.append("| " + " | ".join(cells) + " |")
    log_every = sorted({r["log_every"] for per_run in norms for r in per_run if r is not None})
    if not log_every:
        rows_text = "no run logs it"
    elif log_every == [1]:
        rows_text = "each log row holds one update's (`train.log_every` 1)"
    else:
        rows_text = f"each log row holds its mean over {' or '.join(map(str, log_every))} updates (`train.log_every`)"
    lines += ["", "Frames to threshold: the runs that reach it (mean, 95% t-interval) and how many do not; "
              "Welch's test counts a run that never reaches it at its last frame. Success: mean over the seeds "
              "and its 95% t-interval. p –: the test is undefined (fewer than two runs, or no spread). "
              f"Gradient norm, the whole update's before clipping: {rows_text}; the range of the runs' medians "
              "over their rows, then the range of all rows.", *_differences(variants)]
    return "\n".join(lines)
