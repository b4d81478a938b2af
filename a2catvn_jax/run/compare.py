"""Variants of different experiments side by side, from their stored summaries.

An experiment's report tests each variant against its own first variant only. A
comparison across experiments (the same agent at two gradient-norm clips, each in its
own experiment; a variant against another experiment's control) reads what the
reports already stored: `STORE/SCALE/EXPERIMENT.json` (written by `run_experiment`,
with every number per seed) and, for the gradient norms, the `metrics.jsonl` and
`config.yaml` of each run it lists. Nothing is trained or evaluated.

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
from a2catvn_jax.run import experiments as ex
from a2catvn_jax.run.checkpoint import CheckpointError, read_run_config


class CompareError(UserError):
    """A comparison that cannot be made: a malformed VARIANT, a summary or a run not stored."""


def _parse(spec: str) -> tuple[str, str]:
    name, sep, label = spec.partition(":")
    if not sep or not name or not label:
        raise CompareError(f"{spec!r}: name a variant as EXPERIMENT:LABEL, e.g. 'aux:A2C+UNREAL'")
    return name, label


def load_variants(specs: Sequence[str], scale: str = "cpu", store=ex.DEFAULT_STORE) -> list[dict]:
    """The stored summary entry of each `EXPERIMENT:LABEL` in `specs`, with "experiment",
    "label" and "threshold" added. Raises `CompareError` naming what is missing."""
    if len(specs) < 2:
        raise CompareError(f"compare needs at least two variants, got {len(specs)}")
    store = Path(store)
    summaries, out = {}, []
    for spec in specs:
        name, label = _parse(spec)
        if name not in summaries:
            path = store / scale / f"{name}.json"
            if not path.is_file():
                hint = (f"report it first: python -m a2catvn_jax.experiments {name} --stored-seeds"
                        if name in ex.EXPERIMENTS else "experiments: " + ", ".join(ex.EXPERIMENTS))
                raise CompareError(f"no stored summary of {name!r} at {scale} scale ({path}); {hint}")
            try:
                summaries[name] = json.loads(path.read_text())
            except (OSError, ValueError) as err:
                raise CompareError(f"{path} cannot be read as an experiment summary: {err}") from None
        summary = summaries[name]
        variants = summary.get("variants", {})
        if label not in variants:
            raise CompareError(f"{name} has no reported variant {label!r}; its variants: "
                               + ", ".join(map(repr, variants)))
        out.append({**variants[label], "experiment": name, "label": label, "threshold": summary["threshold"]})
    thresholds = sorted({v["threshold"] for v in out})
    if len(thresholds) > 1:
        raise CompareError("the variants' reports use different success thresholds ("
                           + ", ".join(f"{v['experiment']}: {v['threshold']:g}" for v in out)
                           + "): their frames to threshold cannot be compared")
    return out


def gradient_norms(variant: dict, store=ex.DEFAULT_STORE) -> Optional[dict]:
    """Per run of `variant`: the median, smallest and largest logged gradient norm (the whole
    update's, before clipping), how many logged updates exceed the run's clip
    (`train.max_grad_norm` of its stored configuration, read as training reads an older
    run's) and how many were logged; None when the logs have no norm."""
    runs = []
    for rel in variant["runs"]:
        directory = Path(store) / rel
        try:
            rows = [json.loads(line) for line in (directory / "metrics.jsonl").read_text().splitlines() if line]
            clip = float(read_run_config(directory).train.max_grad_norm)
        except (OSError, ValueError, CheckpointError) as err:
            raise CompareError(f"stored run {directory} cannot be read: {err}") from None
        norms = np.array([r["grad_norm"] for r in rows if r.get("grad_norm") is not None], float)
        if norms.size == 0:
            return None
        runs.append({"median": float(np.median(norms)), "min": float(norms.min()), "max": float(norms.max()),
                     "clip": clip, "above": int((norms > clip).sum()), "logged": int(norms.size)})
    return {"runs": runs}


def _norm_cells(norms: Optional[dict]) -> list[str]:
    if norms is None:
        return ["–", "–"]
    runs = norms["runs"]
    medians = [r["median"] for r in runs]
    clips = sorted({r["clip"] for r in runs})
    spread = f"{min(medians):.2f}" if len(medians) == 1 else f"{min(medians):.2f}–{max(medians):.2f}"
    return [f"{spread}; {min(r['min'] for r in runs):.2f}–{max(r['max'] for r in runs):.2f}",
            f"{sum(r['above'] for r in runs)}/{sum(r['logged'] for r in runs)} "
            f"(clip {', '.join(f'{c:g}' for c in clips)})"]


def _capped(variant: dict) -> list[float]:
    return [variant["frames_max"] if f is None else f for f in variant["frames_to_threshold"]]


def _present(values) -> list[float]:
    return [v for v in values if v is not None and math.isfinite(v)]


def _p_text(p: Optional[float]) -> str:
    return "–" if p is None else f"{p:.2g}"


def compare(specs: Sequence[str], scale: str = "cpu", store=ex.DEFAULT_STORE) -> str:
    """A markdown table of the variants `specs` (`EXPERIMENT:LABEL`, from the stored
    summaries at `scale`) and Welch's tests of each against the first."""
    variants = load_variants(specs, scale, store)
    houses = [h for h in ex.EVAL_SETS if any(h in v["eval"] for v in variants)]
    threshold = variants[0]["threshold"]
    head = ["variant", "experiment", "seeds", f"frames to success {threshold:g}", "final training success",
            *(f"success, {ex.EVAL_SETS[h]}" for h in houses),
            "gradient norm: the runs' medians; all logged", "logged updates above the clip"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for v in variants:
        cells = [v["label"], v["experiment"], ex._seeds_text(v["seeds"]),
                 ex.format_frames(v["frames_to_threshold"], v["frames_max"]), ex.format_estimate(v["final_success"])]
        cells += [ex.format_estimate(v["eval"][h]["success_rate"]) if h in v["eval"] else "–" for h in houses]
        cells += _norm_cells(gradient_norms(v, store))
        lines.append("| " + " | ".join(cells) + " |")
    first, others = variants[0], variants[1:]
    tests = [(f"frames to {threshold:g}", _capped), ("final training success", lambda v: _present(v["final_success"]))]
    tests += [(f"success, {ex.EVAL_SETS[h]}", lambda v, h=h: _present(v["eval"][h]["success_rate"]))
              for h in houses if all(h in v["eval"] for v in variants)]
    head = [f"Welch's p against {first['label']} ({first['experiment']})", *(what for what, _ in tests)]
    lines += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for v in others:
        cells = [f"{v['label']} ({v['experiment']})", *(_p_text(ex.welch_p(values(first), values(v)))
                                                         for _, values in tests)]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Frames to threshold: the runs that reach it (mean, 95% t-interval) and how many do not; "
              "Welch's test counts a run that never reaches it at its last frame. Success: mean over the seeds "
              "and its 95% t-interval. Gradient norm, the whole update's before clipping: the range of the runs' "
              "medians over their logged updates; the range of all logged norms."]
    return "\n".join(lines)
