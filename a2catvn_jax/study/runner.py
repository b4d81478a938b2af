"""An experiment from start to report: plan its runs, train what is neither stored nor
finished, evaluate and store each run, then summarise, plot and write its section.

`run_experiment(exp, Options(...))` goes through four steps: `select_runs` (the plan,
or only the stored runs for a part-way report), `train_missing` (in this process, or
`jobs` at a time in processes of their own, `workers.run_pool`), `evaluate_run` for
each run (with each policy of `EVAL_POLICIES`, sampled and greedy, in each house set,
with the run's evaluation seed `store.eval_seed`) and `baselines` for the policies that
need no training (both cached in the store), and `report` (the JSON summary
`STORE/SCALE/NAME.json`, the figure `DOCS/experiments/NAME_SCALE.png` and the section of
`DOCS/results.md`). An evaluation that is not stored and cannot be made here (no
checkpoint, with `skip_missing`; nothing at all with `evaluate=False`) falls back on the
stored one of that run, houses and policy with the most episodes, and the section says
what each number rests on.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import shlex
import sys
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import jax

from a2catvn_jax.agent.update import total_updates
from a2catvn_jax.errors import Interrupted
from a2catvn_jax.run.evaluation import baselines_for, evaluate_baseline, evaluate_sets
from a2catvn_jax.run.pretraining import PRETRAINED_DIR, pretrain
from a2catvn_jax.run.training import train
from a2catvn_jax.study import report as rp
from a2catvn_jax.study import store as st
from a2catvn_jax.study.registry import BASELINE_LABELS, EVAL_SETS, SCALES, Experiment, ExperimentError
from a2catvn_jax.study.stats import EVAL_POLICIES, summarise
from a2catvn_jax.study.store import DEFAULT_EPISODES, DEFAULT_ROOT, DEFAULT_STORE, Run
from a2catvn_jax.study.workers import run_pool

DEFAULT_SEEDS = (0, 1, 2, 3, 4)
Log = Callable[[str], None]


@dataclasses.dataclass(frozen=True)
class Options:
    """How to run an experiment.

    Runs stored in `store` are not trained again, and their curves and evaluations come
    from the store; the others are trained in `root`, evaluated and stored. `threshold`
    replaces the experiment's success-rate threshold at this scale; `skip_missing` leaves
    out evaluations a stored run lacks and cannot make here (no checkpoint) instead of
    raising `ExperimentError`; `compilation_cache` keeps compiled programs in
    ROOT/.jax_cache (a process-wide JAX setting). `train_only` (variant labels) trains
    only those variants' runs; while runs of the others are neither stored nor trained,
    nothing is reported. `stored_only` trains nothing and reports the stored runs among
    `seeds`, however many each variant has (a variant with none stored yet is left out
    and named; the first variant, the reference, needs one). `jobs` > 1 trains that many
    runs at once, each in a process of its own pinned to its share of the CPU cores;
    `report=False` stops after the training (what those processes do). `evaluate=False`
    trains and evaluates nothing: each number comes from the store, the evaluation asked
    for (`episodes`, the run's evaluation seed) where it is stored, else the stored one
    with the most episodes, as with `skip_missing` (the section says which); runs not
    stored are not reported. `command` is the command line the report quotes.
    """

    scale: str = "cpu"
    seeds: tuple[int, ...] = DEFAULT_SEEDS
    episodes: int = DEFAULT_EPISODES
    root: Path = DEFAULT_ROOT
    docs: Path = Path("docs")
    store: Path = DEFAULT_STORE
    overrides: tuple[str, ...] = ()
    command: str = ""
    threshold: Optional[float] = None
    skip_missing: bool = False
    compilation_cache: bool = True
    train_only: Optional[tuple[str, ...]] = None
    jobs: int = 1
    report: bool = True
    stored_only: bool = False
    evaluate: bool = True

    def __post_init__(self):
        for name in ("root", "docs", "store"):
            object.__setattr__(self, name, Path(getattr(self, name)))
        object.__setattr__(self, "seeds", tuple(self.seeds))
        object.__setattr__(self, "overrides", tuple(self.overrides))
        if self.train_only is not None:
            object.__setattr__(self, "train_only", tuple(self.train_only))
        if self.scale not in SCALES:
            raise ExperimentError(f"scale must be one of {SCALES}, got {self.scale!r}")
        if not self.seeds:
            raise ExperimentError("at least one seed is needed")
        if len(set(self.seeds)) != len(self.seeds):
            raise ExperimentError(f"seeds must differ, got {list(self.seeds)}")
        if self.episodes < 1:
            raise ExperimentError(f"episodes must be >= 1, got {self.episodes}")
        if self.threshold is not None and not 0.0 < self.threshold <= 1.0:
            raise ExperimentError(f"threshold must be in (0, 1], got {self.threshold}")

    def threshold_for(self, exp: Experiment) -> float:
        return exp.threshold_at(self.scale) if self.threshold is None else self.threshold


# -- training ---------------------------------------------------------------------------


def compilation_cache(directory: Path) -> None:
    """Keep compiled programs on disk: seeds of a variant (same shapes and scenes) compile once."""
    if jax.config.jax_compilation_cache_dir is None:
        jax.config.update("jax_compilation_cache_dir", str(directory.absolute()))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def train_run(run: Run, log: Log) -> float:
    """Train `run` to its end (resuming it if it was interrupted); returns the seconds it took now."""
    saved = st.saved_updates(run.workdir)
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
            log(f"pre-training {run.name}")
            pretrain(run.cfg, init_from, log=lambda _: None)
    log(f"{'resuming' if resume else 'training'} {run.name} in {run.workdir}")
    _, state, _ = train(run.cfg, run.workdir, resume=resume, progress=False, log=lambda _: None, init_from=init_from)
    seconds = time.perf_counter() - t0
    timing = run.workdir / "experiment_time.json"
    spent = json.loads(timing.read_text())["seconds"] if timing.exists() else 0.0
    timing.write_text(json.dumps({"seconds": spent + seconds}) + "\n")
    if int(state.update) < total_updates(run.cfg):  # Ctrl-C or SIGTERM: checkpointed, not finished
        raise Interrupted(f"interrupted: {run.name} stopped at update {int(state.update)} of "
                          f"{total_updates(run.cfg)} with a checkpoint in {run.workdir}; the same command "
                          f"resumes it")
    return seconds


def run_command(exp: Experiment, run: Run, opts: Options, python: str = sys.executable) -> list[str]:
    """The command line that trains, evaluates and stores one run of `exp` by itself (what
    `--jobs` processes run and `--plan` prints)."""
    return [python, "-m", "a2catvn_jax.experiments", exp.name, "--scale", opts.scale,
            "--seeds", str(run.seed), "--train-only", run.variant.label, "--episodes", str(opts.episodes),
            "--root", str(opts.root), "--store", str(opts.store), "--docs", str(opts.docs), "--no-report",
            *(["--set", *opts.overrides] if opts.overrides else [])]


def unfinished(runs: list[Run], opts: Options) -> list[Run]:
    """The runs to train (of the `train_only` variants), one per work directory (variants
    with the same configuration share a run), seed by seed."""
    to_train = {}  # work directory -> run
    for run in sorted(runs, key=lambda r: r.seed):
        if not run.is_stored() and (opts.train_only is None or run.variant.label in opts.train_only):
            to_train.setdefault(run.workdir, run)
    return list(to_train.values())


def plan_commands(exp: Experiment, opts: Options, python: str = "python") -> list[str]:
    """One self-contained shell command per unfinished run of `exp`: any scheduler (a
    SLURM job array, another machine) can run them, each storing its run in `opts.store`."""
    _, runs, _ = select_runs(exp, opts, lambda _: None)
    return [shlex.join(run_command(exp, run, opts, python)) for run in unfinished(runs, opts)]


def train_in_processes(exp: Experiment, runs: list[Run], opts: Options, log: Log) -> None:
    """Train, evaluate and store `runs`, `opts.jobs` at a time, each in its own process on
    its share of the cores (`workers.run_pool`); raises `ExperimentError` naming the runs
    that failed and their logs."""
    def command(run: Run) -> list[str]:
        return run_command(exp, run, opts)

    logs = [run.workdir / "train.log" for run in runs]
    t0 = time.perf_counter()

    def started(i, cores):
        log(f"started {runs[i].name} on core(s) {','.join(map(str, cores))}; log: {logs[i]}")

    def ended(i, code):
        minutes = (time.perf_counter() - t0) / 60
        state = "stored" if code == 0 and runs[i].is_stored() else f"FAILED (exit status {code})"
        log(f"{state}: {runs[i].name} ({minutes:.1f} min after the start)")

    log(f"training {len(runs)} run(s), {opts.jobs} at a time, each in its own process")
    codes = run_pool([command(run) for run in runs], opts.jobs, logs, on_start=started, on_end=ended)
    failed = [f"{run.name} (log: {path})" for run, path, code in zip(runs, logs, codes)
              if code != 0 or not run.is_stored()]
    if failed:
        raise ExperimentError(f"{len(failed)} of {len(runs)} run(s) failed: " + "; ".join(failed))


def train_missing(exp: Experiment, runs: list[Run], opts: Options, log: Log) -> None:
    """Train, evaluate and store the runs (of the `train_only` variants) that are not
    stored, seed by seed (every variant of seed 0, then of seed 1, ...: an experiment
    stopped part-way leaves comparable seeds behind); variants with the same
    configuration share one run."""
    to_train = {run.workdir: run for run in unfinished(runs, opts)}
    if opts.jobs > 1 and to_train:
        train_in_processes(exp, list(to_train.values()), opts, log)
    for i, run in sorted(enumerate(runs), key=lambda ir: ir[1].seed):
        if run.is_stored() or run.workdir not in to_train:
            continue
        log(f"[{i + 1}/{len(runs)}] {run.name}")
        seconds = train_run(run, log)
        if seconds:
            log(f"  trained in {seconds / 60:.1f} min")
        st.store_run(run, evaluate_run(run, exp.evaluations, opts.episodes, log=log))
        log(f"  stored in {run.stored}")


# -- evaluation -------------------------------------------------------------------------


def _fallback(run: Run, missing: dict, results: dict, log: Log, why: str) -> None:
    """Put in `results` (policy -> houses -> result), for each missing (policy, houses),
    the stored evaluation with the most episodes (None when there is none), and log what
    each rests on in one line."""
    said: dict = {}  # what -> [houses, policy]
    for p, hs in missing.items():
        for h in hs:
            stored = st.stored_evaluations(run, h, p)
            results[p][h] = stored[0] if stored else None
            what = (f"stored {stored[0]['episodes']} episodes, seed {stored[0].get('seed', st.LEGACY_EVAL_SEED)}"
                    if stored else "none stored, left out")
            said.setdefault(what, []).append(f"{h} {p}")
    log(f"{why}: {run.name}: " + "; ".join(f"{', '.join(where)}: {what}" for what, where in said.items()))


def evaluate_run(run: Run, houses: Sequence[str], episodes: int, policies: Sequence[str] = EVAL_POLICIES, *,
                 skip_missing: bool = False, evaluate: bool = True, log: Log = lambda _: None) -> dict:
    """policy -> houses -> the evaluation of the run's last checkpoint in those houses,
    `episodes` episodes with the run's evaluation seed (`store.eval_seed`).

    Each result is read from the store, else from the work directory's cache; the
    missing ones are evaluated together from the final checkpoint (one restore per set
    of houses, one compile for the sets of one shape), cached and, for a stored run,
    added to the store. Without that checkpoint: `ExperimentError`, or with
    `skip_missing` the stored evaluation of that run, houses and policy with the most
    episodes (`store.stored_evaluations`; None when there is none). With `evaluate=False`
    nothing is evaluated: every missing result falls back so."""
    seed = st.eval_seed(run.seed)
    results = {p: st.saved_evaluations(run, houses, episodes, p, seed) for p in policies}
    missing = {p: [h for h in houses if h not in results[p]] for p in policies}
    missing = {p: hs for p, hs in missing.items() if hs}
    if not missing:
        return results
    if not evaluate or not st.has_final_checkpoint(run):
        if evaluate and not skip_missing:
            stored = sorted(p.name for p in run.stored.glob("eval_*.json"))
            what = "; ".join(f"{', '.join(hs)} houses with {p} policy" for p, hs in missing.items())
            raise ExperimentError(
                f"{run.name} ({run.stored}): no stored evaluation in {what}, {episodes} episodes, seed {seed} "
                f"(stored: {', '.join(stored) or 'none'}), and its final checkpoint is not in {run.workdir}; "
                f"pass --skip-missing (or --no-evaluate) to report the stored evaluations instead")
        _fallback(run, missing, results, log, "not evaluated (--no-evaluate)" if not evaluate else
                  f"no checkpoint for the {episodes} episodes with seed {seed} asked for")
        return results
    groups: dict = {}  # the houses missing -> the policies missing there
    for p, hs in missing.items():
        groups.setdefault(tuple(hs), []).append(p)
    for hs, ps in groups.items():
        log(f"evaluating {run.name} in {', '.join(hs)} ({', '.join(ps)}; {episodes} episodes, seed {seed})")
        fresh = evaluate_sets(run.workdir, episodes, houses=hs, policies=ps, seed=seed, log=lambda _: None)
        for p in ps:
            for h in hs:
                results[p][h] = fresh[(h, p)]
                st.save_evaluation(run, h, p, episodes, results[p][h])
    return results


def baselines(exp: Experiment, scale: str, cfg, houses: Sequence[str], episodes: int, store=DEFAULT_STORE,
              log: Log = lambda _: None, evaluate: bool = True) -> dict:
    """policy -> houses -> the result of each baseline (`BASELINE_LABELS`) that applies
    (`evaluation.baselines_for`: the tour on room-type goals only) in the experiment's
    environment with `episodes` and seed `store.BASELINE_EVAL_SEED`, cached in
    STORE/SCALE/CONFIG/baselines/. With `evaluate=False` one not stored falls back on
    the stored one with the most episodes (`store.stored_baselines`), else is None."""
    out: dict = {}
    seed = st.BASELINE_EVAL_SEED
    for policy in baselines_for(cfg.env):
        out[policy] = {}
        for h in houses:
            result = st.saved_baseline(exp, scale, cfg, policy, h, episodes, store, seed)
            if result is None and not evaluate:
                stored = st.stored_baselines(exp, scale, cfg, policy, h, store)
                result = stored[0] if stored else None
                log(f"not evaluated (--no-evaluate): the {BASELINE_LABELS[policy]} in {EVAL_SETS[h]}: "
                    + (f"the stored evaluation of {result['episodes']} episodes with seed "
                       f"{result.get('seed', st.LEGACY_EVAL_SEED)} is reported instead" if result else
                       "none stored, left out"))
            elif result is None:
                log(f"evaluating the {BASELINE_LABELS[policy]} in {EVAL_SETS[h]} ({episodes} episodes, seed {seed})")
                path = st.baseline_path(exp, scale, cfg, policy, h, episodes, store, seed)
                st.save_result(path, evaluate_baseline(cfg, episodes, houses=h, policy=policy, seed=seed,
                                                       log=lambda _: None))
                result = json.loads(path.read_text())
            out[policy][h] = result
    return out


# -- the whole experiment ---------------------------------------------------------------


def select_runs(exp: Experiment, opts: Options, log: Log) -> tuple[Experiment, list[Run], list[str]]:
    """The experiment as reported (without the variants a part-way report leaves out),
    its runs, and the labels of the variants left out."""
    labels = [v.label for v in exp.variants]
    unknown = [label for label in opts.train_only or () if label not in labels]
    if unknown:
        raise ExperimentError(f"{exp.name} has no variant {', '.join(map(repr, unknown))}; its variants: "
                              + ", ".join(map(repr, labels)))
    runs = st.plan(exp, opts.scale, opts.seeds, opts.root, opts.overrides, opts.store)
    if not opts.stored_only:
        return exp, runs, []
    runs = [r for r in runs if r.is_stored()]
    not_stored = [v.label for v in exp.variants if not any(r.variant == v for r in runs)]
    if exp.variants[0].label in not_stored:  # the reference every other variant is tested against
        raise ExperimentError(f"{exp.name}: no run of {exp.variants[0].label!r} (the variant the others are "
                              f"compared with) is stored in {opts.store}")
    if not_stored:
        log(f"{exp.name}: left out of this part-way report, none of their runs stored yet: "
            + ", ".join(map(repr, not_stored)))
        exp = dataclasses.replace(exp, variants=tuple(v for v in exp.variants if v.label not in not_stored))
    return exp, runs, not_stored


def report(exp: Experiment, runs: list[Run], opts: Options, not_stored: list[str], log: Log, t0: float) -> dict:
    """Summarise the stored `runs` with their evaluations and the baselines, and write
    the summary's JSON, its figure and its section; returns the summary (`t0`: when the
    experiment started, for the log)."""
    records = [st.run_record(run, evaluate_run(run, exp.evaluations, opts.episodes, skip_missing=opts.skip_missing,
                                               evaluate=opts.evaluate, log=log)) for run in runs]
    base_cfg = st.task_config(exp, opts.scale, opts.overrides)
    baseline = baselines(exp, opts.scale, base_cfg, exp.evaluations, opts.episodes, opts.store, log, opts.evaluate)
    summary = summarise(exp, records, baseline, opts.threshold_for(exp))
    used = sorted({n for v in summary["variants"].values() for e in v["eval"].values() for n in e["episodes"]
                   if n is not None})
    summary.update(scale=opts.scale, episodes=opts.episodes, episodes_used=used, eval_seed_offset=st.EVAL_SEED_OFFSET,
                   baseline_eval_seed=st.BASELINE_EVAL_SEED, policies=list(EVAL_POLICIES),
                   max_episode_steps=runs[0].cfg.env.max_episode_steps,
                   overrides=list(opts.overrides), command=opts.command, not_stored=not_stored)
    out_json = opts.store / opts.scale / f"{exp.name}.json"
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(summary, indent=1) + "\n")
    image = opts.docs / "experiments" / f"{exp.name}_{opts.scale}.png"
    rp.plot(summary, image, f"{exp.title} ({opts.scale} scale, configs/{exp.config_path(opts.scale).name})")
    rp.write_section(opts.docs / "results.md", exp, opts.scale,
                     rp.section(exp, opts.scale, summary, opts.command, image.relative_to(opts.docs).as_posix()))
    log(f"wrote {image}, {out_json} and its section of {opts.docs / 'results.md'} in {time.perf_counter() - t0:.0f} s")
    log(rp.table(summary, exp.evaluations))
    log(rp.evaluation_table(summary, exp.evaluations))
    return summary


def run_experiment(exp: Experiment, opts: Options = Options(), log: Optional[Log] = None) -> dict:
    """Train, evaluate, store and report `exp` (`Options`); returns its summary (also
    written as JSON). With runs of other variants than `train_only` neither stored nor
    trained, nothing is reported and the summary is {"experiment": name, "pending": [run
    names]}: a long experiment can be trained a variant at a time, across sittings and
    machines, through the store. With `report=False`: {"experiment": name, "trained":
    [the stored runs]}."""
    log = log or functools.partial(print, flush=True)
    t0 = time.perf_counter()
    exp, runs, not_stored = select_runs(exp, opts, log)
    if opts.compilation_cache:
        compilation_cache(opts.root / ".jax_cache")
    stored = sum(r.is_stored() for r in runs)
    log(f"{exp.name}: {len(runs)} runs, {stored} stored in {opts.store}, {len(runs) - stored} to train or finish")
    if opts.evaluate:
        train_missing(exp, runs, opts, log)
    if not opts.report:
        return {"experiment": exp.name, "trained": [run.name for run in runs if run.is_stored()]}
    pending = [run.name for run in runs if not run.is_stored()]
    if pending:
        log(f"not reported: {len(pending)} run(s) neither stored nor trained now: {', '.join(pending)}")
        return {"experiment": exp.name, "pending": pending}
    return report(exp, runs, opts, not_stored, log, t0)
