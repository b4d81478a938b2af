"""The results store: where each run of an experiment lives, and what of it is kept.

`plan` gives every (variant, seed) run two directories named by its run key
(`run_key`), so a variant two experiments share is trained once:

- its work directory under ROOT (default `runs/experiments`): checkpoints, TensorBoard
  files and the full training log, on the machine that trained it;
- its stored copy under STORE (default `results`, inside the repository):
  `STORE/SCALE/CONFIG/RUN_KEY/seed_N/` with config.yaml, variant.json, metrics.jsonl
  (the columns of `STORED_COLUMNS`, 4 significant digits), the evaluation results
  (`eval_HOUSES_POLICY_EPISODES_seedS.json`, S the evaluation seed, `eval_seed`: 1000 +
  the run's seed; older ones, `eval_HOUSES_POLICY_EPISODES.json`, hold seed 0),
  experiment_time.json, pretrain_metrics.jsonl (pre-trained variants), eval.jsonl
  (the evaluations during training of experiments that make them, `curve_overrides`)
  and, written last, done.json (updates, frames, date, machine, git commit).

The run key hashes the configuration's values that differ from the schema's defaults
(`Config()`), the seed and `train.eval` left out, and whether the run starts from pre-training: a key
added to the configuration with its default leaves every key as it was. Baselines that
need no training are cached in `STORE/SCALE/CONFIG/baselines/`, named by `env_key`, the
same hash of the environment section alone, and by their evaluation seed
(`BASELINE_EVAL_SEED`). A run with a done.json is finished: it is never trained again and
its curves and evaluations are read from here. An evaluation is used only for the
episodes and seed it records (`matches`); `stored_evaluations` lists every one a run
keeps, for a report that falls back on them.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import hashlib
import json
import math
import shutil
from pathlib import Path
from typing import Mapping, Optional, Sequence


from a2catvn_jax.agent.update import total_updates
from a2catvn_jax.config import Config, load_config, save_config, to_dict
from a2catvn_jax.configio import flat
from a2catvn_jax.run.checkpoint import CONFIG_FILE, EVAL_KEYS, Checkpointer
from a2catvn_jax.run.evaluation import to_json
from a2catvn_jax.run.logger import read_jsonl
from a2catvn_jax.study import provenance
from a2catvn_jax.study.registry import Experiment, Variant
from a2catvn_jax.study.stats import RunRecord

DEFAULT_ROOT = Path("runs/experiments")
DEFAULT_STORE = Path("results")
# The training-log columns a stored run keeps (the curves, the plots, the learning-rate
# and complexity schedules, the gradient norm); the full log stays in the work directory.
STORED_COLUMNS = ("update", "frames", "complexity", "episodes", "success_rate", "episode_length", "spl",
                  "episode_return", "grad_norm", "loss/total")
DONE = "done.json"
EVAL_LOG = "eval.jsonl"  # the rows of the evaluations during training (run/training_eval.py)
BASELINE_DIR = "baselines"
EVAL_SEED_OFFSET = 1000  # a run of seed S is evaluated with seed EVAL_SEED_OFFSET + S
DEFAULT_EPISODES = 500  # per run, house set and policy: Wilson's interval at 0.5 is about +-0.044
CURVE_EPISODES = DEFAULT_EPISODES  # per evaluation during training (`curve_overrides`), as many as the final ones
BASELINE_EVAL_SEED = EVAL_SEED_OFFSET - 1  # the baselines' own: below every run's (run seeds are >= 0)
LEGACY_EVAL_SEED = 0  # what every evaluation stored without a seed in its name used


# -- keys -------------------------------------------------------------------------------


def non_defaults(values: Mapping, defaults: Mapping) -> dict:
    """dotted key -> value for every leaf of the nested `values` that differs from its
    value in the nested `defaults` (or that `defaults` lacks); lists are compared whole."""
    flat_defaults = flat(defaults)
    return {k: v for k, v in flat(values).items() if k not in flat_defaults or flat_defaults[k] != v}


def _hash(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:8]


def config_key(values: Mapping, defaults: Mapping, pretrain: bool = False) -> str:
    """8 hex digits naming a configuration (nested dicts, e.g. `to_dict(cfg)`) by its
    values that differ from `defaults`, its seed and evaluation during training
    (`train.eval`) left out, and pre-trained or not: the canonical JSON (sorted dotted
    keys) of those differences, hashed."""
    differences = {k: v for k, v in non_defaults({k: v for k, v in values.items() if k != "seed"}, defaults).items()
                   if k not in EVAL_KEYS}
    return _hash(json.dumps(differences, sort_keys=True) + ("|pretrain" if pretrain else ""))


@functools.cache
def _defaults() -> dict:
    return to_dict(Config())


def run_key(cfg, pretrain: bool) -> str:
    """The run key of a (configuration without its seed, pre-trained or not) pair: a run is
    reused exactly for its configuration, and a key added to the schema with its default
    renames no run. A changed default does not rename the runs whose configuration leaves
    that key at its default, though they were trained with the old one."""
    return config_key(to_dict(cfg), _defaults(), pretrain)


def env_key(cfg) -> str:
    """8 hex digits naming the environment section of a configuration (what a baseline
    depends on) by its values that differ from the defaults."""
    return _hash(json.dumps(non_defaults(to_dict(cfg)["env"], _defaults()["env"]), sort_keys=True))


# -- runs -------------------------------------------------------------------------------


@dataclasses.dataclass
class Run:
    variant: Variant
    seed: int
    cfg: object
    workdir: Path  # checkpoints, TensorBoard and the full log (this machine only)
    stored: Path  # the stored copy of its small results (committed)

    @property
    def name(self) -> str:
        return f"{self.variant.label}, seed {self.seed}"

    @property
    def relative(self) -> str:
        """SCALE/CONFIG/RUN_KEY/seed_N: where the run is under ROOT and STORE."""
        return "/".join(self.stored.parts[-4:])

    def is_stored(self) -> bool:
        return (self.stored / DONE).is_file()


def curve_overrides(exp: Experiment, cfg, seed: int) -> list[str]:
    """The `train.eval` settings of a run of `exp` (configuration `cfg`): `held_out_points`
    evaluations in held-out houses over the run, each of CURVE_EPISODES sampled episodes
    with the run's evaluation seed (the last is its final held-out evaluation)."""
    if not exp.held_out_points:
        return []
    every = max(1, total_updates(cfg) // exp.held_out_points)
    return [f"train.eval.every={every}", f"train.eval.episodes={CURVE_EPISODES}", "train.eval.houses=[held-out]",
            "train.eval.policies=[sample]", f"train.eval.seed={eval_seed(seed)}"]


def task_config(exp: Experiment, scale: str, overrides: Sequence[str] = ()) -> Config:
    """The configuration `exp`'s variants start from and its baselines run in: its
    configuration file with its `setting` and `overrides`."""
    return load_config(exp.config_path(scale), [*exp.setting, *overrides])


def plan(exp: Experiment, scale: str, seeds: Sequence[int], root=DEFAULT_ROOT, overrides: Sequence[str] = (),
         store=DEFAULT_STORE) -> list[Run]:
    """The runs of `exp`: every variant with every seed, configurations checked (with
    `curve_overrides`), each at ROOT|STORE/SCALE/CONFIG/RUN_KEY/seed_N."""
    path = exp.config_path(scale)
    runs = []
    for variant in exp.variants:
        base = load_config(path, [*exp.setting, *overrides, *variant.overrides])
        key = run_key(base, variant.pretrain)
        relative = Path(scale) / exp.config / key
        for seed in seeds:
            cfg = load_config(path, [*exp.setting, *overrides, *variant.overrides, f"seed={seed}",
                                     *curve_overrides(exp, base, seed)])
            where = relative / f"seed_{seed}"
            runs.append(Run(variant, seed, cfg, Path(root) / where, Path(store) / where))
    return runs


def stored_runs(exp: Experiment, scale: str, store=DEFAULT_STORE, overrides: Sequence[str] = ()) -> dict:
    """variant label -> {seed: its stored directory} for the finished runs in `store`."""
    out = {}
    for variant in exp.variants:
        key_dir = plan(dataclasses.replace(exp, variants=(variant,)), scale, [0], store=store,
                       overrides=overrides)[0].stored.parent
        seeds = sorted(int(d.name[5:]) for d in key_dir.glob("seed_*") if d.name[5:].isdigit() and (d / DONE).is_file())
        out[variant.label] = {seed: key_dir / f"seed_{seed}" for seed in seeds}
    return out


def stored_seeds(exp: Experiment, scale: str, store=DEFAULT_STORE, overrides: Sequence[str] = ()) -> dict:
    """variant label -> the seeds stored (finished) for it, sorted."""
    return {label: sorted(runs) for label, runs in stored_runs(exp, scale, store, overrides).items()}


def saved_updates(workdir: Path) -> list[int]:
    """The update counts of the checkpoints in `workdir` (none if it has no checkpoint yet)."""
    if not (workdir / "checkpoints").is_dir():
        return []
    ckpt = Checkpointer(workdir, create=False)
    try:
        return ckpt.steps()
    finally:
        ckpt.close()


def has_final_checkpoint(run: Run) -> bool:
    return max(saved_updates(run.workdir), default=0) >= total_updates(run.cfg)


def training_seconds(run: Run) -> Optional[float]:
    """Wall time the run took to train (pre-training and compilation included), if recorded."""
    for directory in (run.stored, run.workdir):
        timing = directory / "experiment_time.json"
        if timing.exists():
            return json.loads(timing.read_text())["seconds"]
    return None


# -- what is stored ---------------------------------------------------------------------


def rounded(value, digits: int = 4):
    """Floats to `digits` significant digits (what a stored file keeps); anything else as is."""
    if isinstance(value, float) and math.isfinite(value) and value != 0.0:
        return float(f"{value:.{digits}g}")
    if isinstance(value, list):
        return [rounded(v, digits) for v in value]
    if isinstance(value, dict):
        return {k: rounded(v, digits) for k, v in value.items()}
    return value


def _without_repeats(rows: list[dict]) -> list[dict]:
    """Log rows with those an interrupted run wrote after its last checkpoint replaced by
    the resumed run's rows of the same updates."""
    kept: list[dict] = []
    for row in rows:
        while kept and "update" in row and kept[-1].get("update", -1) >= row["update"]:
            kept.pop()
        kept.append(row)
    return kept


def trim_log(rows: list[dict]) -> list[dict]:
    """The stored form of a training log: `STORED_COLUMNS`, 4 significant digits."""
    return [{k: rounded(row[k]) for k in STORED_COLUMNS if k in row} for row in _without_repeats(rows)]


def _write_jsonl(path: Path, rows: list[dict]) -> None:
    path.write_text("".join(json.dumps(row, allow_nan=True) + "\n" for row in rows))


def eval_seed(run_seed: int) -> int:
    """The evaluation seed of a run of seed `run_seed`: other episodes than any the run
    trained on, the same for every variant of one seed (the variants of seed S meet the
    same goals and starts), and for both policies."""
    return EVAL_SEED_OFFSET + run_seed


def eval_name(houses: str, policy: str, episodes: int, seed: Optional[int] = None) -> str:
    """eval_HOUSES_POLICY_EPISODES_seedSEED.json (seed None: the older name, no seed)."""
    return f"eval_{houses}_{policy}_{episodes}" + ("" if seed is None else f"_seed{seed}") + ".json"


def matches(result: dict, episodes: int, seed: int, step: Optional[int] = None) -> bool:
    """Whether a stored evaluation is the one asked for: its episodes and seed as it
    records them (an older result without a seed used `LEGACY_EVAL_SEED`), and `step`."""
    return (result.get("episodes") == episodes and result.get("seed", LEGACY_EVAL_SEED) == seed
            and (step is None or result.get("step") == step))


def stored_result(result: dict) -> dict:
    """An evaluation result as stored: no machine path, floats rounded."""
    return rounded({k: v for k, v in result.items() if k not in ("workdir", "video")})


def store_run(run: Run, evals: dict) -> None:
    """Copy the small results of the finished, evaluated `run` (policy -> houses -> result,
    each named by its own policy, episodes and seed) to its stored directory; done.json
    goes last, so a copy that was interrupted is not taken for a finished run."""
    d = run.stored
    d.mkdir(parents=True, exist_ok=True)
    (d / DONE).unlink(missing_ok=True)
    if (run.workdir / CONFIG_FILE).is_file():
        shutil.copyfile(run.workdir / CONFIG_FILE, d / "config.yaml")
    else:
        save_config(run.cfg, d / "config.yaml")
    (d / "variant.json").write_text(json.dumps(dataclasses.asdict(run.variant), indent=1) + "\n")
    rows = trim_log(read_jsonl(run.workdir / "metrics.jsonl"))
    _write_jsonl(d / "metrics.jsonl", rows)
    if (run.workdir / EVAL_LOG).is_file():
        _write_jsonl(d / EVAL_LOG, [rounded(r) for r in read_jsonl(run.workdir / EVAL_LOG)])
    pre = run.workdir / "pretrain" / "pretrain_metrics.jsonl"
    if pre.is_file():
        _write_jsonl(d / "pretrain_metrics.jsonl", [rounded(r) for r in read_jsonl(pre)])
    for by_houses in evals.values():
        for houses, result in by_houses.items():
            if result is not None:
                name = eval_name(houses, result["policy"], result["episodes"], result["seed"])
                (d / name).write_text(to_json(stored_result(result)))
    seconds = training_seconds(run)
    if seconds is not None:
        (d / "experiment_time.json").write_text(json.dumps({"seconds": round(seconds, 1)}) + "\n")
    done = {"updates": total_updates(run.cfg), "frames": rows[-1]["frames"] if rows else None,
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "machine": provenance.machine(), "git": provenance.git_commit()}
    (d / DONE).write_text(json.dumps(done, indent=1) + "\n")


def done_record(run: Run) -> dict:
    return json.loads((run.stored / DONE).read_text())


def stored_log(run: Run) -> list[dict]:
    """The rows of the run's stored metrics.jsonl."""
    return read_jsonl(run.stored / "metrics.jsonl")


def run_record(run: Run, evals: dict) -> RunRecord:
    """What the statistics use of the stored `run`, with its evaluations (policy -> houses -> result)."""
    eval_log = tuple(read_jsonl(run.stored / EVAL_LOG)) if (run.stored / EVAL_LOG).is_file() else ()
    return RunRecord(run.variant, run.seed, run.relative, stored_log(run), evals, training_seconds(run),
                     done_record(run), eval_log)


# -- evaluations and baselines ----------------------------------------------------------


def _cached(run: Run, houses: str, policy: str, episodes: int, seed: int) -> Path:
    """Where the work directory keeps an evaluation (the run may not be stored yet)."""
    return run.workdir / f"experiment_{eval_name(houses, policy, episodes, seed)}"


def _read(path: Path) -> Optional[dict]:
    try:
        result = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return result if isinstance(result, dict) else None


def saved_evaluations(run: Run, houses: Sequence[str], episodes: int, policy: str = "sample",
                      seed: Optional[int] = None) -> dict:
    """houses -> the evaluation of the run's final checkpoint with `policy`, `episodes`
    and evaluation `seed` (default `eval_seed(run.seed)`), for those the store or the
    work directory's cache has (an older file without the seed in its name counts when
    its recorded seed is `seed`); one found in the cache of a stored run is added to the store."""
    seed = eval_seed(run.seed) if seed is None else seed
    results = {}
    updates = total_updates(run.cfg)
    for h in houses:
        named = run.stored / eval_name(h, policy, episodes, seed)
        for path in (named, run.stored / eval_name(h, policy, episodes), _cached(run, h, policy, episodes, seed)):
            result = _read(path) if path.is_file() else None
            if result is not None and result.get("policy", policy) == policy and matches(result, episodes, seed,
                                                                                         updates):
                results[h] = result
                if path.parent != run.stored and run.is_stored():
                    named.write_text(to_json(stored_result(result)))
                break
    return results


def stored_evaluations(run: Run, houses: str, policy: str) -> list[dict]:
    """Every evaluation of the run's final checkpoint in `houses` with `policy` that the
    store keeps, whatever its episodes and seed: the most episodes first, then the
    lowest seed."""
    updates = total_updates(run.cfg)
    found = [_read(p) for p in sorted(run.stored.glob(f"eval_{houses}_{policy}_*.json"))]
    found = [r for r in found if r is not None and r.get("step") == updates and r.get("houses", houses) == houses
             and r.get("policy", policy) == policy and isinstance(r.get("episodes"), int)]
    return sorted(found, key=lambda r: (-r["episodes"], r.get("seed", LEGACY_EVAL_SEED)))


def save_evaluation(run: Run, houses: str, policy: str, episodes: int, result: dict) -> None:
    """Cache a fresh evaluation in the work directory, and add it to the store if the run is stored."""
    _cached(run, houses, policy, episodes, result["seed"]).write_text(to_json(result))
    if run.is_stored():
        (run.stored / eval_name(houses, policy, episodes, result["seed"])).write_text(to_json(stored_result(result)))


def baseline_path(exp: Experiment, scale: str, cfg, policy: str, houses: str, episodes: int,
                  store=DEFAULT_STORE, seed: Optional[int] = BASELINE_EVAL_SEED) -> Path:
    """STORE/SCALE/CONFIG/baselines/POLICY_HOUSES_EPISODES_seedSEED_ENVKEY.json (seed None:
    the older name without it, seed 0)."""
    seeded = "" if seed is None else f"_seed{seed}"
    return Path(store) / scale / exp.config / BASELINE_DIR / f"{policy}_{houses}_{episodes}{seeded}_{env_key(cfg)}.json"


def saved_baseline(exp: Experiment, scale: str, cfg, policy: str, houses: str, episodes: int,
                   store=DEFAULT_STORE, seed: int = BASELINE_EVAL_SEED) -> Optional[dict]:
    """The stored baseline result with these episodes and seed (either file name), or None."""
    for path in (baseline_path(exp, scale, cfg, policy, houses, episodes, store, seed),
                 baseline_path(exp, scale, cfg, policy, houses, episodes, store, None)):
        result = _read(path) if path.is_file() else None
        if result is not None and matches(result, episodes, seed):
            return result
    return None


def stored_baselines(exp: Experiment, scale: str, cfg, policy: str, houses: str, store=DEFAULT_STORE) -> list[dict]:
    """Every stored result of baseline `policy` in `houses` of the environment of `cfg`,
    whatever its episodes and seed: the most episodes first, then the lowest seed."""
    directory = Path(store) / scale / exp.config / BASELINE_DIR
    found = [_read(p) for p in sorted(directory.glob(f"{policy}_{houses}_*_{env_key(cfg)}.json"))]
    found = [r for r in found if r is not None and r.get("policy") == policy and r.get("houses") == houses
             and isinstance(r.get("episodes"), int)]
    return sorted(found, key=lambda r: (-r["episodes"], r.get("seed", LEGACY_EVAL_SEED)))


def save_result(path: Path, result: dict) -> None:
    """Store an evaluation result (a baseline's) at `path`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(to_json(stored_result(result)))
