"""An experiment's report: its figure, its tables and its section of docs/results.md.

`plot` draws the learning curves of a summary (`stats.summarise`), `table` (training and
sampled evaluation), `evaluation_table` (both policies, seed- and episode-level
intervals), `distance_table` (success by the start's distance from the goal),
`evaluation_basis` (the episodes and seeds each evaluation number rests on)
and `section` write its markdown, `write_section` puts a section between its markers in
results.md, and `listing` counts the seeds stored for each variant. The number formats
are `formats`'s, shared with `compare`.
"""

from __future__ import annotations

import json
import math
import re
import textwrap
from collections import Counter
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import EngFormatter

from a2catvn_jax.study.formats import format_estimate, format_frames, format_pooled, format_rmst, frames_text, seeds_text
from a2catvn_jax.study.registry import BASELINE_LABELS, BASELINE_STYLES, EVAL_SETS, EXPERIMENTS, SCALES, Experiment
from a2catvn_jax.study.stats import (FINAL_FRACTION, SMOOTH_FRACTION, episode_successes, pooled_success,
                                     success_by_distance)
from a2catvn_jax.study.store import (BASELINE_DIR, CURVE_EPISODES, DEFAULT_STORE, DONE, LEGACY_EVAL_SEED, plan,
                                     stored_runs)

POLICY_NAMES = {"sample": "sampled", "greedy": "greedy"}
EVAL_KEYS = {"sample": "eval", "greedy": "eval_greedy"}  # where a summary's variant keeps each policy's numbers


def reference_houses(summary: dict) -> Optional[str]:
    """The house set whose baselines the curves show: the training houses when evaluated."""
    sets = [h for policy in summary["baselines"].values() for h in policy]
    return "train" if "train" in sets else (sets[0] if sets else None)


def plot(summary: dict, out, title: str) -> None:
    """Success rate and episode length against frames: the mean over seeds, shaded with
    its 95% t-band; horizontal lines for the threshold and the baselines. Where runs
    evaluated held-out houses during training, a third panel: that success, the mean
    over those runs with its band, and the baselines in held-out houses."""
    rows = math.ceil((len(summary["variants"]) + 3) / 3)  # legend rows below the panels
    height = 3.4 + 0.17 * rows
    curves = {label: v.get("held_out_curve") for label, v in summary["variants"].items()}
    held_out = any(c is not None for c in curves.values())
    fig = Figure(figsize=(15 if held_out else 10, height))
    axes = fig.subplots(1, 3 if held_out else 2)
    threshold = summary["threshold"]
    limits = {"success_rate": 1.0, "episode_length": summary["max_episode_steps"]}
    for label, v in summary["variants"].items():
        frames = np.array(v["frames"])
        n = len(v["seeds"])
        reached = sum(f is not None for f in v["frames_to_threshold"])
        legend = f"{label} ({n} seed{'s' if n > 1 else ''}; {reached}/{n} reach {threshold:g})"
        for ax, key in zip(axes, ("success_rate", "episode_length")):
            mean, half = np.array(v[key]["mean"]), np.array(v[key]["half_width_95"])
            line, = ax.plot(frames, mean, label=legend)
            if n > 1:
                ax.fill_between(frames, np.clip(mean - half, 0, limits[key]), np.clip(mean + half, 0, limits[key]),
                                color=line.get_color(), alpha=0.2, linewidth=0)
        if curves[label] is not None:
            c = curves[label]
            mean, half = np.array(c["mean"]), np.array(c["half_width_95"])
            axes[2].plot(c["frames"], mean, marker="o", color=line.get_color())
            if c["runs"] > 1:
                axes[2].fill_between(c["frames"], np.clip(mean - half, 0, 1), np.clip(mean + half, 0, 1),
                                     color=line.get_color(), alpha=0.2, linewidth=0)
        elif held_out:
            axes[2].plot([], [], color=line.get_color())  # keeps the colours of the other panels
    axes[0].axhline(threshold, color="grey", linestyle=":", linewidth=1, label=f"threshold {threshold:g}")
    houses = reference_houses(summary)
    for policy, style in BASELINE_STYLES.items():
        result = summary["baselines"].get(policy, {}).get(houses)
        if result is not None:
            name = f"{BASELINE_LABELS[policy]} ({EVAL_SETS[houses]})"
            axes[0].axhline(result["success_rate"], color="black", linestyle=style, linewidth=1, label=name)
            axes[1].axhline(result["episode_length"], color="black", linestyle=style, linewidth=1)
    if held_out:
        for policy, style in BASELINE_STYLES.items():
            result = summary["baselines"].get(policy, {}).get("held-out")
            if result is not None:
                axes[2].axhline(result["success_rate"], color="black", linestyle=style, linewidth=1)
        axes[2].set_ylim(0, 1.02)
    axes[0].set_ylim(0, 1.02)
    axes[1].set_ylim(0, summary["max_episode_steps"] * 1.02)
    for ax, name in zip(axes, ("training success rate", "training episode length",
                               "held-out success (sampled), during training")):
        ax.set_xlabel("frames")
        ax.xaxis.set_major_formatter(EngFormatter(sep=""))
        ax.set_title(name)
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=7, frameon=False)
    fig.suptitle(textwrap.fill(title, 120), fontsize=10)  # a long description wraps, not clips
    fig.tight_layout(rect=(0, 0.17 * rows / height + 0.02, 1, 1))
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)


def table(summary: dict, evaluations: Sequence[str]) -> str:
    """The markdown table of a summary: per variant, the mean over seeds and its 95%
    t-interval; then the baselines' evaluation numbers."""
    threshold = summary["threshold"]
    head = ["variant", f"frames to success {threshold:g}",
            f"restricted mean frames to {threshold:g}, up to {frames_text(summary['rmst_horizon'])}",
            "final training success", f"change over the last {FINAL_FRACTION:.0%}"]
    for h in evaluations:
        head += [f"success, {EVAL_SETS[h]}", f"SPL, {EVAL_SETS[h]}"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label, v in summary["variants"].items():
        cells = [label, format_frames(v["frames_to_threshold"], v["frames_max"]), format_rmst(v.get("rmst_frames")),
                 format_estimate(v["final_success"]), format_estimate(v["late_change"], -1.0, 1.0, "{:+.2f}".format)]
        for h in evaluations:
            cells += [format_estimate(v["eval"][h]["success_rate"]), format_estimate(v["eval"][h]["spl"])]
        lines.append("| " + " | ".join(cells) + " |")
    for policy, label in _reported_baselines(summary, evaluations):
        cells = [label, "–", "–", "–", "–"]
        for h in evaluations:
            r = summary["baselines"].get(policy, {}).get(h)
            cells += ["–", "–"] if r is None else [f"{r['success_rate']:.2f}", f"{r['spl']:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _reported_baselines(summary: dict, evaluations: Sequence[str]) -> list[tuple[str, str]]:
    """(policy, label) of the random policy, the oracle, and the other baselines that
    have a result in some of `evaluations` (the tour: on room-type goals)."""
    return [(p, label) for p, label in BASELINE_LABELS.items()
            if p in ("random", "oracle") or any(summary["baselines"].get(p, {}).get(h) for h in evaluations)]


def _tour_text(summary: dict) -> str:
    if not any(summary["baselines"].get("tour", {}).values()):
        return ""
    return (f" The {BASELINE_LABELS['tour']} (`env.tour`), evaluated like the baselines, knows the map but not the "
            f"goal: it heads for the nearest room it has not yet looked into, looks at the objects that show that "
            f"room's type from where the oracle would, and goes on until the episode ends. It recognises nothing, "
            f"so its success and SPL are what searching with a map reaches by finding alone (densely dotted in the "
            f"curves).")


def _baseline_pooled(result: dict) -> dict:
    return pooled_success([episode_successes(result)], [result["episodes"]])


def evaluation_table(summary: dict, evaluations: Sequence[str]) -> str:
    """Evaluation success with each policy: per variant and policy, the mean over seeds
    with its t-interval, success over all episodes pooled across seeds with Wilson's
    interval, and SPL; then the baselines (one evaluation each: Wilson's interval)."""
    head = ["variant", "policy"]
    for h in evaluations:
        head += [f"success, {EVAL_SETS[h]}: seeds", f"success, {EVAL_SETS[h]}: episodes", f"SPL, {EVAL_SETS[h]}"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label, v in summary["variants"].items():
        for policy, key in EVAL_KEYS.items():
            cells = [label, POLICY_NAMES[policy]]
            for h in evaluations:
                e = v.get(key, {}).get(h) or {}
                values = e.get("success_rate", [None] * len(v["seeds"]))
                cells += [format_estimate(values), format_pooled(e.get("pooled"), len(v["seeds"])),
                          format_estimate(e.get("spl", values))]
            lines.append("| " + " | ".join(cells) + " |")
    for policy, label in _reported_baselines(summary, evaluations):
        cells = [label, "–"]
        for h in evaluations:
            r = summary["baselines"].get(policy, {}).get(h)
            cells += ["–", "–", "–"] if r is None else ["–", format_pooled(_baseline_pooled(r)), f"{r['spl']:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _distance_cell(by: Optional[dict], band: int) -> str:
    if by is None or by["episodes"][band] == 0:
        return "–"
    return f"{by['successes'][band] / by['episodes'][band]:.2f} ({by['episodes'][band]})"


def distance_table(summary: dict, houses: str) -> str:
    """Sampled success in `houses` by the geodesic distance from the start to the goal:
    per variant over its episodes pooled across seeds, then the baselines; each cell the
    rate and (the episodes in that band). Empty when no evaluation there has per-episode
    distances."""
    rows = [(label, (v.get("eval", {}).get(houses) or {}).get("by_distance")) for label, v in summary["variants"].items()]
    rows += [(label, success_by_distance([summary["baselines"].get(policy, {}).get(houses)]))
             for policy, label in _reported_baselines(summary, [houses])]
    rows = [(label, by) for label, by in rows if by is not None]
    if not rows:
        return ""
    edges = rows[0][1]["edges"]
    bands = [f"{lo:g}–{hi:g} m" for lo, hi in zip([0.0, *edges[:-1]], edges)] + [f"{edges[-1]:g} m or more"]
    lines = ["| " + " | ".join([f"success, {EVAL_SETS[houses]}, by start distance", *bands]) + " |",
             "|" + "---|" * (len(bands) + 1)]
    for label, by in rows:
        lines.append("| " + " | ".join([label, *(_distance_cell(by, i) for i in range(len(bands)))]) + " |")
    return "\n".join(lines)


def _basis_text(key: tuple, offset: Optional[int]) -> str:
    episodes, seed = key
    return f"{episodes} episodes, " + (f"seed {offset} + the run's seed" if seed == "asked" else f"seed {seed}")


def evaluation_basis(summary: dict, evaluations: Sequence[str]) -> str:
    """What every evaluation number rests on, in words: per policy, the episodes and
    seeds of the runs' evaluations (per variant, house set and seed where they differ),
    and whether they are the ones asked for or stored ones reported instead; then the
    baselines'."""
    asked, offset = summary.get("episodes"), summary.get("eval_seed_offset")
    asked_key = (asked, "asked")
    parts = []
    for policy, key in EVAL_KEYS.items():
        cells = {}  # (label, houses) -> {basis: [run seeds]}
        missing = total = 0
        for label, v in summary["variants"].items():
            n = len(v["seeds"])
            for h in evaluations:
                e = v.get(key, {}).get(h) or {}
                for run_seed, episodes, seed in zip(v["seeds"], e.get("episodes") or [None] * n,
                                                    e.get("eval_seed") or [None] * n):
                    total += 1
                    if episodes is None:
                        missing += 1
                        continue
                    seed = LEGACY_EVAL_SEED if seed is None else seed
                    basis = (episodes, "asked" if offset is not None and seed == offset + run_seed else seed)
                    cells.setdefault((label, h), {}).setdefault(basis, []).append(run_seed)
        name = f"{POLICY_NAMES[policy]} policy"
        kinds = {basis for by in cells.values() for basis in by}
        if not kinds:
            parts.append(f"{name}: none stored")
            continue
        if len(kinds) == 1:
            (kind,) = kinds
            text = f"{name}: {kind[0]} episodes per run and house set, " + _basis_text(kind, offset).split(", ", 1)[1]
            if kind != asked_key:
                text += (f" (stored evaluations, reported instead of the {_basis_text(asked_key, offset)} asked for, "
                         f"which are not stored and need the runs' checkpoints)")
        else:
            text = (f"{name}, evaluations that differ (asked for: {_basis_text(asked_key, offset)}): " + "; ".join(
                f"{label}, {EVAL_SETS[h]}: " + ", ".join(
                    f"seed{'s' if len(seeds) > 1 else ''} {seeds_text(seeds)} {_basis_text(kind, offset)}"
                    for kind, seeds in by.items()) for (label, h), by in cells.items()))
        if missing:
            text += f"; {missing} of {total} evaluations (runs x house sets) not stored, left out"
        parts.append(text)
    seed_asked = summary.get("baseline_eval_seed")
    base = [(policy, h, r["episodes"], r.get("seed", LEGACY_EVAL_SEED))
            for policy, by_h in summary["baselines"].items() for h, r in by_h.items() if r is not None]
    kinds = {(episodes, seed) for _, _, episodes, seed in base}
    if len(kinds) == 1:
        (episodes, seed), = kinds
        text = f"baselines: {episodes} episodes, seed {seed}"
        if (episodes, seed) != (asked, seed_asked):
            text += f" (stored, reported instead of the {asked} episodes with seed {seed_asked} asked for)"
        parts.append(text)
    elif kinds:
        parts.append(f"baselines, evaluations that differ (asked for: {asked} episodes, seed {seed_asked}): " + "; ".join(
            f"{BASELINE_LABELS[p]}, {EVAL_SETS[h]}: {episodes} episodes, seed {seed}" for p, h, episodes, seed in base))
    return "; ".join(parts)


def _provenance(summary: dict) -> str:
    """Where, when and from which commit the runs were trained (from their done.json)."""
    trained = [t for v in summary["variants"].values() for t in v["trained"]]
    machines = Counter(t["machine"] or "unknown" for t in trained)
    dates = sorted(t["date"][:10] for t in trained if t["date"])
    commits = Counter((t["git"] or {}).get("commit", "unknown")[:10]
                      + ("+changes" if (t["git"] or {}).get("dirty") else "") for t in trained)
    text = "Trained on " + "; ".join(f"{m} ({k} run{'s' if k > 1 else ''})" for m, k in machines.most_common())
    if dates:
        text += f", {dates[0]}" + (f" to {dates[-1]}" if dates[-1] != dates[0] else "")
    return text + "; code: " + ", ".join(f"{c} ({k})" for c, k in commits.most_common()) + "."


def _mean_minutes(seconds: Sequence[Optional[float]]) -> str:
    known = [s for s in seconds if s is not None]
    return f"{np.mean(known) / 60:.1f} min" if known else "not recorded"


BLIND_TEXTS = {  # agent.blind -> what the section says of a variant with it
    "true": "The blind variant (`agent.blind=true`) trains like the others on images of zeros: what it reaches "
            "needs no sight.",
    "target": "The target-blind variant (`agent.blind=target`) sees its observations but a target image of zeros: "
              "it can learn the houses, not which goal it is given.",
    "observation": "The observation-blind variant (`agent.blind=observation`) sees the target image but "
                   "observations of zeros: it knows the goal, not where it is.",
}


def _blind_text(exp: Experiment) -> str:
    modes = [mode for mode in BLIND_TEXTS if any(f"agent.blind={mode}" in v.overrides for v in exp.variants)]
    return "".join(" " + BLIND_TEXTS[mode] for mode in modes)


def _held_out_text(summary: dict) -> str:
    """What the third panel shows, when runs evaluated held-out houses during training."""
    counts = {label: v["held_out_curve"]["runs"] for label, v in summary["variants"].items()
              if v.get("held_out_curve") is not None}
    if not counts:
        return ""
    return (f" Third panel: success in held-out houses during training (`train.eval`: {CURVE_EPISODES} sampled "
            f"episodes per point with the run's evaluation seed, the same episodes at every point), the mean over "
            f"the runs that made these evaluations (" + "; ".join(f"{label} {n}" for label, n in counts.items())
            + ") with its 95% t-band; dashed and dash-dotted: the random policy and the oracle there.")


def section(exp: Experiment, scale: str, summary: dict, command: str, image: str) -> str:
    evaluations = exp.evaluations
    seeds = {label: v["seeds"] for label, v in summary["variants"].items()}
    first_seeds = next(iter(seeds.values()))
    n = min(len(s) for s in seeds.values())
    if all(s == first_seeds for s in seeds.values()):
        seeds_line = f"{seeds_text(first_seeds)} ({n} run{'s' if n > 1 else ''} per variant)"
    else:  # a part-way report (`stored_only`)
        seeds_line = "; ".join(f"{label} {seeds_text(s)} ({len(s)})" for label, s in seeds.items())
    threshold = summary["threshold"]
    lines = [
        f"### {exp.title} ({scale} scale)",
        "",
        f"Command: `{command}`  ",
        f"Configuration: `configs/{exp.config_path(scale).name}`"
        + (f" with `{' '.join(exp.setting)}`" if exp.setting else "") + "; variants: "
        + "; ".join(f"{v.label}" + (f" (`{' '.join(v.overrides)}`)" if v.overrides else "")
                    + (" (pre-trained)" if v.pretrain and "pre-trained" not in v.label else "")
                    for v in exp.variants) + ".  ",
        *([f"Not in this part-way report, no run stored yet: {'; '.join(summary['not_stored'])}.  "]
          if summary.get("not_stored") else []),
        f"Seeds: {seeds_line}. Evaluation at complexity 1: {evaluation_basis(summary, evaluations)}.  ",
        _provenance(summary) + " Mean training wall time per run: "
        + "; ".join(f"{label} {_mean_minutes(v['training_seconds'])}" for label, v in summary["variants"].items())
        + " (compilation and pre-training included).",
        "",
        f"![{exp.name}]({image})",
        "",
        table(summary, evaluations),
        "",
        evaluation_table(summary, evaluations),
        "",
        *([distances, ""] if (distances := distance_table(summary, "held-out")) else []),
        ("One seed: each cell is that run's value, no interval" if max(map(len, seeds.values())) == 1 else
         "Each cell: the mean over the seeds and its 95% t-interval [low, high] (Student's t, n − 1 degrees of "
         "freedom, clipped to the possible range" + ("; a variant with one run: its value, no interval)" if n == 1
                                                     else ")"))
        + "; (n=k): only k runs have that number. "
        f"Frames to threshold: the first log row at which the training success rate, a running mean over "
        f"{SMOOTH_FRACTION:.0%} of the run, reaches {threshold:g}; the mean and interval are over the runs that reach "
        f"it, and the runs that never do are counted. Restricted mean frames to threshold (runs that never reach it "
        f"censored at their last frame): the area under the Kaplan-Meier curve of the share of runs not yet at the "
        f"threshold, from 0 to the shortest run's last frame ({frames_text(summary['rmst_horizon'])}), with its 95% "
        f"interval (Greenwood's variance, normal approximation, clipped to that range); when no run reaches it, that "
        f"horizon exactly. Final training success: the last {FINAL_FRACTION:.0%} of the "
        f"run; its change: that minus the {FINAL_FRACTION:.0%} before it (above 0: still improving when the run "
        f"ended). Evaluation with both policies (second table): sampled, actions drawn from the policy as in "
        f"training; greedy, its most probable action at each step. \"seeds\": the mean over the seeds and its "
        f"t-interval as above; \"episodes\": success over all the variant's evaluation episodes pooled across "
        f"seeds, with Wilson's 95% score interval, which takes the episodes as independent and so leaves out the "
        f"spread between seeds that the t-interval includes. Baselines, evaluated like the runs but with no "
        f"training: a {BASELINE_LABELS['random']} and the {BASELINE_LABELS['oracle']} (`env.oracle`)."
        + (" By start distance (third table): sampled success in held-out houses over the episodes pooled across "
           "seeds, in bands of the geodesic distance from the start to the goal's region (for a room-type goal, the "
           "nearest room of that type; the distance SPL divides by), each cell the rate and, in brackets, the "
           "episodes in that band."
           if distance_table(summary, "held-out") else "")
        + _tour_text(summary)
        + _blind_text(exp)
        + f" Curves: the mean over seeds of the running mean, shaded with its 95% t-band; dotted: the threshold; "
        f"dashed and dash-dotted: the random policy's and the oracle's success rate and episode length in the "
        f"{EVAL_SETS.get(reference_houses(summary), 'evaluated houses')}."
        + _held_out_text(summary),
    ]
    tests = [(label, v["welch_p_frames_vs_first"]) for label, v in summary["variants"].items()][1:]
    if tests and any(p is not None for _, p in tests):
        first = next(iter(summary["variants"]))
        lines += ["", f"Welch's t-test on frames to threshold against {first}, a run that never reaches it counted "
                      f"at the run's last frame: " + "; ".join(f"{label} p = {'–' if p is None else f'{p:.2g}'}"
                                                              for label, p in tests) + "."]
    tests = [(label, v.get("logrank_p_frames_vs_first")) for label, v in summary["variants"].items()][1:]
    if tests and any(p is not None for _, p in tests):
        first = next(iter(summary["variants"]))
        lines += ["", f"Log-rank test on frames to threshold against {first}, a run that never reaches it censored "
                      f"at its last frame: " + "; ".join(f"{label} p = {'–' if p is None else f'{p:.2g}'}"
                                                        for label, p in tests) + "."]
    first = next(iter(summary["variants"]))
    for key, policy in (("welch_p_eval_success_vs_first", ""), ("welch_p_eval_greedy_success_vs_first", ", greedy")):
        for h in evaluations:
            tests = [(label, (v.get(key) or {}).get(h)) for label, v in summary["variants"].items()][1:]
            if tests and any(p is not None for _, p in tests):
                lines += ["", f"Welch's t-test on evaluation success ({EVAL_SETS[h]}{policy}) against {first}: "
                          + "; ".join(f"{label} p = {'–' if p is None else f'{p:.2g}'}" for label, p in tests) + "."]
    if exp.paper:
        lines += ["", f"The paper: {exp.paper}"]
    return "\n".join(lines)


def write_section(results_md: Path, exp: Experiment, scale: str, text: str) -> None:
    """Put `text` between the experiment's markers in `results_md` (appended the first time)."""
    start, end = f"<!-- experiment {exp.name} {scale} -->", f"<!-- end experiment {exp.name} {scale} -->"
    block = f"{start}\n{text}\n{end}"
    old = results_md.read_text() if results_md.exists() else "# Results\n"
    pattern = re.compile(re.escape(start) + r".*?" + re.escape(end), re.S)
    new = pattern.sub(lambda _: block, old) if pattern.search(old) else old.rstrip("\n") + "\n\n" + block + "\n"
    results_md.parent.mkdir(parents=True, exist_ok=True)
    results_md.write_text(new)


def listing(store=DEFAULT_STORE, scales: Sequence[str] = SCALES, names: Optional[Sequence[str]] = None,
            overrides: Sequence[str] = ()) -> str:
    """Per experiment and scale, how many seeds of each variant are stored; then the stored
    run keys no current variant has (runs of another configuration, kept but unused)."""
    lines, known = [], set()
    for exp in EXPERIMENTS.values():
        if names and exp.name not in names:
            continue
        configs = f"{exp.config}.yaml" if exp.cpu_only else f"{exp.config}[_cpu].yaml"
        lines.append(f"{exp.name}: {exp.title} (configs/{configs}; success threshold "
                     f"{exp.threshold:g}, {exp.cpu_threshold:g} at CPU scale)")
        for scale in scales:
            stored = stored_runs(exp, scale, store, overrides)
            keys = {r.variant: r.stored.parent.name for r in plan(exp, scale, [0], store=store, overrides=overrides)}
            for v in exp.variants:
                seeds = sorted(stored[v.label])
                known |= set(stored[v.label].values())
                what = " ".join((*exp.setting, *v.overrides)) or "as configured"
                lines.append(f"  {scale:5s} {v.label}: {len(seeds)} stored"
                             f"{f' (seeds {seeds_text(seeds)})' if seeds else ''}"
                             f" [{keys[v]}: {what}{' + pre-training' if v.pretrain else ''}]")
    others = []
    for scale in scales:
        for config_dir in sorted(p for p in (Path(store) / scale).glob("*") if p.is_dir()):
            for key_dir in sorted(p for p in config_dir.glob("*") if p.is_dir() and p.name != BASELINE_DIR):
                unused = [d for d in key_dir.glob("seed_*") if (d / DONE).is_file() and d not in known]
                if unused:
                    label = json.loads((unused[0] / "variant.json").read_text()).get("label", "")
                    others.append(f"  {scale}/{config_dir.name}/{key_dir.name}: {len(unused)} stored ({label})")
    if others and not names:
        lines += ["stored runs no current variant uses (another configuration; `config.yaml` in each says which):",
                  *others]
    return "\n".join(lines)
