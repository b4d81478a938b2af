"""Comparisons of the method's variants: train with several seeds, evaluate, plot, tabulate.

`EXPERIMENTS` names each comparison: a configuration of `configs/` (`NAME_cpu.yaml`
or `NAME.yaml` by scale) and its variants (overrides, pre-training). `plan` gives
every (variant, seed) run a work directory named by the hash of its configuration,
so a variant two experiments share is trained once; `run_experiment` trains what is
not finished (resuming what was interrupted), evaluates each run in its house sets
(`run.evaluation.evaluate_sets`, cached beside the run) against a uniformly random
policy, and writes the curves, a JSON summary and a section of `docs/results.md`.
The command line and what it writes: `python -m a2catvn_jax.experiments --help`.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import hashlib
import json
import math
import os
import platform
import re
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import jax
import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import EngFormatter
from scipy import stats

from a2catvn_jax.agent.update import total_updates
from a2catvn_jax.config import CONFIGS, load_config, to_dict
from a2catvn_jax.errors import UserError
from a2catvn_jax.run.checkpoint import Checkpointer
from a2catvn_jax.run.evaluation import evaluate_sets, to_json
from a2catvn_jax.run.logger import read_jsonl
from a2catvn_jax.run.plots import smooth
from a2catvn_jax.run.pretraining import PRETRAINED_DIR, pretrain
from a2catvn_jax.run.training import train

SCALES = ("cpu", "paper")
SMOOTH_FRACTION = 0.1  # curves are running means over this fraction of a run's log rows
FINAL_FRACTION = 0.1  # "final" training success: the mean over this last fraction of the rows
EVAL_SETS = {"train": "training houses", "new-targets": "new targets", "held-out": "held-out houses"}

NO_VN = ("train.loss_weights.depth=0", "train.loss_weights.segmentation=0", "train.loss_weights.target_segmentation=0")
NO_UNREAL = ("train.loss_weights.off_policy_critic=0", "train.loss_weights.pixel_control=0",
             "train.loss_weights.reward_prediction=0")


class ExperimentError(UserError, RuntimeError):
    """An experiment cannot run as asked."""


@dataclasses.dataclass(frozen=True)
class Variant:
    label: str
    overrides: tuple[str, ...] = ()
    pretrain: bool = False  # start from `python -m a2catvn_jax.pretrain` with the same configuration and seed


@dataclasses.dataclass(frozen=True)
class Experiment:
    name: str
    title: str
    config: str  # configs/<config>.yaml (paper) and configs/<config>_cpu.yaml (cpu)
    variants: tuple[Variant, ...]
    threshold: float = 0.9  # training success rate for "frames to threshold" at paper scale
    cpu_threshold: float = 0.7  # the same at CPU scale (short runs reach lower rates)
    evaluations: tuple[str, ...] = ("train", "new-targets", "held-out")
    paper: str = ""  # what the paper reports for this comparison

    def threshold_at(self, scale: str) -> float:
        return self.cpu_threshold if scale == "cpu" else self.threshold

    def config_path(self, scale: str) -> Path:
        if scale not in SCALES:
            raise ExperimentError(f"scale must be one of {SCALES}, got {scale!r}")
        return CONFIGS / (f"{self.config}_cpu.yaml" if scale == "cpu" else f"{self.config}.yaml")


EXPERIMENTS = {e.name: e for e in (
    Experiment(
        "aux", "A2CAT-VN vs A2C+UNREAL vs A2C", "image_goals",
        (Variant("A2CAT-VN"), Variant("A2C+UNREAL", NO_VN), Variant("A2C", NO_VN + NO_UNREAL)),
        paper="House3D, 16 houses: average episode length 200 after about 3M frames with the visual-navigation "
              "auxiliary tasks, about 8M without them (A2C+UNREAL); plain A2C is not shown.",
    ),
    Experiment(
        "memory", "LSTM vs frame stack", "maze",
        (Variant("LSTM"), Variant("frame stack", ("agent.memory=frame_stack",))),
        paper="DeepMind Lab SeekAvoid, UNREAL auxiliary tasks: the LSTM clearly outperforms four stacked frames.",
    ),
    Experiment(
        "pretraining", "with vs without supervised pre-training", "image_goals",
        (Variant("no pre-training"), Variant("pre-trained", pretrain=True)),
        paper="Pre-training is part of the House3D run (2e4 images, 30 epochs of Adam); the paper reports no "
              "ablation of it and names its effect as future work.",
    ),
    Experiment(
        "curriculum", "with vs without the curriculum", "image_goals",
        (Variant("no curriculum"), Variant("curriculum", ("train.curriculum=true",))),
        paper="The curriculum (complexity 0.3 to 1.0 between 5M and 10M frames) is part of the House3D run; "
              "the paper reports no ablation of it.",
    ),
    Experiment(
        "generalisation", "room-type goals in 16 houses: training vs held-out houses", "house_rooms",
        (Variant("A2CAT-VN"),),
        cpu_threshold=0.5,
        paper="The paper leaves generalisation to unseen houses and unseen targets as future work.",
    ),
    Experiment(
        "clipping", "gradient-norm clipping with the auxiliary losses", "image_goals",
        (Variant("A2CAT-VN, clip 0.5"), Variant("A2CAT-VN, clip 40", ("train.max_grad_norm=40",)),
         Variant("A2C, clip 0.5", NO_VN + NO_UNREAL)),
        paper="Table I clips the global gradient norm at 0.5. The auxiliary losses add to that norm, so the clip "
              "also shrinks the actor-critic part of the step; the paper does not discuss this.",
    ),
    Experiment(
        "grid", "grid actions on small rooms: A2CAT-VN vs A2C", "grid",
        (Variant("A2CAT-VN"), Variant("A2C", NO_VN + NO_UNREAL)),
        paper="AI2-THOR, four scenes, grid actions: A2CAT-VN finds the optimal solution after about 5e5 frames.",
    ),
)}


# -- runs -----------------------------------------------------------------------------


def run_key(cfg, pretrain: bool) -> str:
    """8 hex digits naming a (configuration without its seed, pre-trained or not) pair."""
    data = to_dict(cfg)
    data.pop("seed")
    text = json.dumps(data, sort_keys=True) + ("|pretrain" if pretrain else "")
    return hashlib.sha256(text.encode()).hexdigest()[:8]


@dataclasses.dataclass
class Run:
    variant: Variant
    seed: int
    cfg: object
    workdir: Path


def plan(exp: Experiment, scale: str, seeds: Sequence[int], root, overrides: Sequence[str] = ()) -> list[Run]:
    """The runs of `exp`: every variant with every seed, configurations checked."""
    path = exp.config_path(scale)
    runs = []
    for variant in exp.variants:
        base = load_config(path, [*overrides, *variant.overrides])
        key = run_key(base, variant.pretrain)
        for seed in seeds:
            cfg = load_config(path, [*overrides, *variant.overrides, f"seed={seed}"])
            runs.append(Run(variant, seed, cfg, Path(root) / scale / exp.config / key / f"seed_{seed}"))
    return runs


def _saved_updates(workdir: Path) -> list[int]:
    """The update counts of the checkpoints in `workdir` (none if it has no checkpoint yet)."""
    if not (workdir / "checkpoints").is_dir():
        return []
    ckpt = Checkpointer(workdir, create=False)
    try:
        return ckpt.steps()
    finally:
        ckpt.close()


def train_run(run: Run, log: Callable[[str], None]) -> float:
    """Train `run` to its end (resuming it if it was interrupted); returns the seconds it took now."""
    saved = _saved_updates(run.workdir)
    if max(saved, default=0) >= total_updates(run.cfg):
        return 0.0
    t0 = time.perf_counter()
    run.workdir.mkdir(parents=True, exist_ok=True)
    (run.workdir / "variant.json").write_text(json.dumps(dataclasses.asdict(run.variant), indent=1) + "\n")
    resume = bool(saved)  # a run stopped before its first checkpoint starts again from scratch
    init_from = None
    if run.variant.pretrain and not resume:
        init_from = run.workdir / "pretrain"
        if not (init_from / PRETRAINED_DIR).is_dir():
            log(f"pre-training {run.variant.label}, seed {run.seed}")
            pretrain(run.cfg, init_from, log=lambda _: None)
    log(f"{'resuming' if resume else 'training'} {run.variant.label}, seed {run.seed} in {run.workdir}")
    train(run.cfg, run.workdir, resume=resume, progress=False, log=lambda _: None, init_from=init_from)
    seconds = time.perf_counter() - t0
    timing = run.workdir / "experiment_time.json"
    spent = json.loads(timing.read_text())["seconds"] if timing.exists() else 0.0
    timing.write_text(json.dumps({"seconds": spent + seconds}) + "\n")
    return seconds


def training_seconds(run: Run) -> Optional[float]:
    """Wall time the run took to train (pre-training and compilation included), if recorded."""
    timing = run.workdir / "experiment_time.json"
    return json.loads(timing.read_text())["seconds"] if timing.exists() else None


def evaluate_run(run: Run, houses: Sequence[str], episodes: int, policy: str = "sample") -> dict:
    """houses -> the evaluation of the run's last checkpoint in those houses, each cached
    in its work directory; the missing ones are evaluated together (one restore, one
    compile for the sets of one shape)."""
    def path(h):
        return run.workdir / f"experiment_eval_{h}_{policy}_{episodes}.json"

    results = {}
    for h in houses:
        if path(h).exists():
            result = json.loads(path(h).read_text())
            if result["step"] == total_updates(run.cfg):
                results[h] = result
    missing = [h for h in houses if h not in results]
    if missing:
        fresh = evaluate_sets(run.workdir, episodes, houses=missing, policies=(policy,), log=lambda _: None)
        for h in missing:
            results[h] = fresh[(h, policy)]
            path(h).write_text(to_json(results[h]))
    return results


# -- statistics -------------------------------------------------------------------------


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
    return mean, stats.t.ppf(0.975, n - 1) * standard_error(values, axis)


def training_log(run: Run) -> list[dict]:
    """The rows of the run's metrics.jsonl."""
    return read_jsonl(run.workdir / "metrics.jsonl")


def curves(rows: list[dict]) -> dict:
    """frames, and the smoothed success rate, episode length and SPL of a training log."""
    k = max(1, round(SMOOTH_FRACTION * len(rows)))
    frames = np.array([r["frames"] for r in rows], float)
    out = {"frames": frames}
    for key in ("success_rate", "episode_length", "spl"):
        out[key] = smooth(np.array([r.get(key, np.nan) for r in rows], float), k)
    return out


def frames_to_threshold(curve: dict, threshold: float) -> Optional[float]:
    """The first logged frame count at which the smoothed success rate reaches `threshold`."""
    hit = np.nonzero(curve["success_rate"] >= threshold)[0]
    return float(curve["frames"][hit[0]]) if hit.size else None


def final_success(rows: list[dict]) -> float:
    """The mean training success rate over the last FINAL_FRACTION of a training log."""
    tail = rows[-max(1, round(FINAL_FRACTION * len(rows))):]
    values = [r["success_rate"] for r in tail if r.get("success_rate") is not None and math.isfinite(r["success_rate"])]
    return float(np.mean(values)) if values else math.nan


def summarise(exp: Experiment, runs: list[Run], evals: dict, baseline: dict, threshold: float) -> dict:
    """Per variant: curves (mean and interval), frames to threshold, final and evaluation numbers."""
    variants = {}
    for variant in exp.variants:
        mine = [r for r in runs if r.variant == variant]
        logs = [training_log(r) for r in mine]
        cs = [curves(rows) for rows in logs]
        n = min(len(c["frames"]) for c in cs)
        entry = {"seeds": [r.seed for r in mine], "workdirs": [str(r.workdir) for r in mine],
                 "frames": cs[0]["frames"][:n].tolist()}
        for key in ("success_rate", "episode_length"):
            stacked = np.stack([c[key][:n] for c in cs])
            mean, half = t_interval(stacked)
            entry[key] = {"mean": mean.tolist(), "sem": standard_error(stacked).tolist(),
                          "half_width_95": half.tolist()}
        entry["frames_to_threshold"] = [frames_to_threshold(c, threshold) for c in cs]
        entry["final_success"] = [final_success(rows) for rows in logs]
        entry["training_seconds"] = [training_seconds(r) for r in mine]
        entry["eval"] = {h: {m: [evals[(str(r.workdir), h)][m] for r in mine] for m in ("success_rate", "spl")}
                         for h in exp.evaluations}
        variants[variant.label] = entry
    return {"experiment": exp.name, "title": exp.title, "threshold": threshold, "variants": variants,
            "random": baseline}


# -- outputs --------------------------------------------------------------------------


def plot(summary: dict, out, title: str) -> None:
    """Success rate and episode length against frames: the mean over seeds, shaded ± one
    standard error (with 2 seeds, exactly the range between them)."""
    fig = Figure(figsize=(9, 3.4))
    axes = fig.subplots(1, 2)
    for label, v in summary["variants"].items():
        frames = np.array(v["frames"])
        for ax, key in zip(axes, ("success_rate", "episode_length")):
            mean, half = np.array(v[key]["mean"]), np.array(v[key]["sem"])
            line, = ax.plot(frames, mean, label=f"{label} ({len(v['seeds'])} seeds)")
            ax.fill_between(frames, mean - half, mean + half, color=line.get_color(), alpha=0.2, linewidth=0)
    axes[0].axhline(summary["threshold"], color="grey", linestyle=":", linewidth=1)
    random = summary["random"].get("train")
    if random is not None:
        axes[0].axhline(random["success_rate"], color="black", linestyle="--", linewidth=1, label="random policy")
    axes[0].set_ylim(0, 1.02)
    axes[1].set_ylim(0, summary["max_episode_steps"] * 1.02)
    for ax, name in zip(axes, ("training success rate", "training episode length")):
        ax.set_xlabel("frames")
        ax.xaxis.set_major_formatter(EngFormatter(sep=""))
        ax.set_title(name)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)


def _mean_pm(values, spec=".2f") -> str:
    values = [v for v in values if v is not None and math.isfinite(v)]
    if not values:
        return "–"
    if len(values) == 1:
        return format(values[0], spec)
    return f"{format(np.mean(values), spec)} ± {format(np.std(values, ddof=1), spec)}"


def _frames(values) -> str:
    reached = [v for v in values if v is not None]
    if not reached:
        return f"not reached (0/{len(values)})"
    text = " ± ".join(part + "k" for part in _mean_pm([v / 1e3 for v in reached], ".0f").split(" ± "))
    return text if len(reached) == len(values) else f"{text} ({len(reached)}/{len(values)} seeds)"


def table(summary: dict, evaluations: Sequence[str]) -> str:
    """The markdown table of a summary: mean ± sd over seeds."""
    head = ["variant", f"frames to success {summary['threshold']:g}", "final training success"]
    for h in evaluations:
        head += [f"success, {EVAL_SETS[h]}", f"SPL, {EVAL_SETS[h]}"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label, v in summary["variants"].items():
        cells = [label, _frames(v["frames_to_threshold"]), _mean_pm(v["final_success"])]
        for h in evaluations:
            cells += [_mean_pm(v["eval"][h]["success_rate"]), _mean_pm(v["eval"][h]["spl"])]
        lines.append("| " + " | ".join(cells) + " |")
    random = summary["random"]
    cells = ["uniformly random policy", "–", "–"]
    for h in evaluations:
        r = random.get(h)
        cells += ["–", "–"] if r is None else [f"{r['success_rate']:.2f}", f"{r['spl']:.2f}"]
    lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    devices = ", ".join(sorted({d.device_kind for d in jax.devices()}))
    return f"{os.cpu_count()}-core {cpu}; jax {jax.__version__} on {jax.default_backend()} ({devices})"


def section(exp: Experiment, scale: str, summary: dict, command: str, image: str) -> str:
    evaluations = exp.evaluations
    v0 = next(iter(summary["variants"].values()))
    lines = [
        f"### {exp.title} ({scale} scale)",
        "",
        f"Command: `{command}`  ",
        f"Configuration: `configs/{exp.config_path(scale).name}`; variants: "
        + "; ".join(f"{v.label}" + (f" (`{' '.join(v.overrides)}`)" if v.overrides else "")
                    + (" (pre-trained)" if v.pretrain else "") for v in exp.variants) + ".  ",
        f"Seeds: {', '.join(map(str, v0['seeds']))}. Evaluation: {summary['episodes']} episodes per run and set, "
        f"sampled policy, complexity 1.  ",
        f"Machine: {summary['machine']}. Date: {summary['date']}. Training wall time per run: "
        + "; ".join(f"{label} {_mean_pm([s / 60 for s in v['training_seconds'] if s is not None], '.1f')} min"
                    for label, v in summary["variants"].items())
        + " (compilation and pre-training included).",
        "",
        f"![{exp.name}]({image})",
        "",
        table(summary, evaluations),
        "",
        f"Mean ± standard deviation over seeds. Frames to threshold: the first log row at which the training "
        f"success rate, a running mean over {SMOOTH_FRACTION:.0%} of the run, reaches {summary['threshold']:g}. Final "
        f"training success: the last {FINAL_FRACTION:.0%} of the run. Curves: the mean over seeds of that running "
        f"mean, shaded ± one standard error (with two seeds, the range between them); the dotted line is the "
        f"threshold, the dashed one the random policy's success rate in the training houses.",
    ]
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


# -- the whole experiment ----------------------------------------------------------------


def _compilation_cache(directory: Path) -> None:
    """Keep compiled programs on disk: seeds of a variant (same shapes and scenes) compile once."""
    if jax.config.jax_compilation_cache_dir is None:
        jax.config.update("jax_compilation_cache_dir", str(directory.absolute()))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def run_experiment(exp: Experiment, *, scale: str = "cpu", seeds: Sequence[int] = (0, 1), episodes: int = 100,
                   root="runs/experiments", docs="docs", overrides: Sequence[str] = (), command: str = "",
                   threshold: Optional[float] = None, compilation_cache: bool = True,
                   log: Optional[Callable[[str], None]] = None) -> dict:
    """Train, evaluate and report `exp`; returns its summary (also written as JSON).

    `threshold` replaces the experiment's success-rate threshold at this scale;
    `compilation_cache` keeps compiled programs in ROOT/.jax_cache (a process-wide JAX setting).
    """
    log = log or functools.partial(print, flush=True)
    if not seeds:
        raise ExperimentError("at least one seed is needed")
    if len(set(seeds)) != len(seeds):
        raise ExperimentError(f"seeds must differ, got {list(seeds)}")
    if episodes < 1:
        raise ExperimentError(f"episodes must be >= 1, got {episodes}")
    threshold = exp.threshold_at(scale) if threshold is None else threshold
    if not 0.0 < threshold <= 1.0:
        raise ExperimentError(f"threshold must be in (0, 1], got {threshold}")
    t0 = time.perf_counter()
    runs = plan(exp, scale, seeds, root, overrides)
    if compilation_cache:
        _compilation_cache(Path(root) / ".jax_cache")
    for i, run in enumerate(runs):
        log(f"[{i + 1}/{len(runs)}] {run.variant.label}, seed {run.seed}")
        seconds = train_run(run, log)
        if seconds:
            log(f"  trained in {seconds / 60:.1f} min")
    evals = {}
    for run in runs:
        for houses, result in evaluate_run(run, exp.evaluations, episodes).items():
            evals[(str(run.workdir), houses)] = result
        log(f"evaluated {run.variant.label}, seed {run.seed}: " + ", ".join(
            f"{h} {evals[(str(run.workdir), h)]['success_rate']:.2f}" for h in exp.evaluations))
    random = evaluate_run(runs[0], exp.evaluations, episodes, policy="random")
    baseline = {h: {k: random[h][k] for k in ("success_rate", "spl")} for h in exp.evaluations}
    summary = summarise(exp, runs, evals, baseline, threshold)
    wall = time.perf_counter() - t0
    summary.update(scale=scale, episodes=episodes, max_episode_steps=runs[0].cfg.env.max_episode_steps, overrides=list(overrides), machine=machine(),
                   date=datetime.date.today().isoformat(), wall_seconds=wall, command=command)
    out_json = Path(root) / scale / f"{exp.name}.json"
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(summary, indent=1) + "\n")
    docs = Path(docs)
    image = docs / "experiments" / f"{exp.name}_{scale}.png"
    plot(summary, image, f"{exp.title} ({scale} scale, configs/{exp.config_path(scale).name})")
    write_section(docs / "results.md", exp, scale,
                  section(exp, scale, summary, command, image.relative_to(docs).as_posix()))
    log(f"wrote {image}, {out_json} and its section of {docs / 'results.md'}")
    log(table(summary, exp.evaluations))
    return summary
