"""Comparisons of the method's variants: train with several seeds, evaluate, store, plot, tabulate.

`EXPERIMENTS` names each comparison: a configuration of `configs/` (`NAME_cpu.yaml`
or `NAME.yaml` by scale) and its variants (overrides, pre-training). `plan` gives
every (variant, seed) run a name from the hash of its configuration, so a variant two
experiments share is trained once. A run has two directories:

- its work directory under ROOT (default `runs/experiments`): checkpoints, TensorBoard
  files and the full training log, on the machine that trained it;
- its stored copy under STORE (default `docs/experiments/runs`, inside the repository):
  `STORE/SCALE/CONFIG/RUN_KEY/seed_N/` with config.yaml, variant.json, metrics.jsonl
  (the columns of `STORED_COLUMNS`, 4 significant digits), the evaluation results
  (`eval_HOUSES_POLICY_EPISODES.json`), experiment_time.json, pretrain_metrics.jsonl
  (pre-trained variants) and, written last, done.json (updates, frames, date, machine,
  git commit).

A run with a done.json in the store is finished: it is not trained again and its
curves and evaluations are read from the store, so committed runs accumulate across
machines and a fresh clone re-plots and re-tabulates without training. The run key
hashes the whole configuration; a run stored under another key still counts when its
saved configuration, read as training reads an older run's (keys added since take their
default or their `LEGACY_VALUES`), equals the planned one. Only an
evaluation the store lacks (another episode count, another house set) needs the
run's last checkpoint in ROOT. Baselines that need no training (a uniformly random
policy, the shortest-path oracle; `run.evaluation.evaluate_baseline`) are cached in
`STORE/SCALE/CONFIG/baselines/`.

`run_experiment` trains what is neither stored nor finished (resuming what was
interrupted), evaluates and stores each run, and writes the curves (mean over seeds,
95% t-band), a JSON summary (`STORE/SCALE/NAME.json`) and a section of
`docs/results.md`. The command line: `python -m a2catvn_jax.experiments --help`.
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
import shutil
import subprocess
import sys
import textwrap
import time
import warnings
from collections import Counter
from pathlib import Path
from typing import Callable, Optional, Sequence

import jax
import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import EngFormatter
from scipy import stats

from a2catvn_jax.agent.update import total_updates
from a2catvn_jax.config import CONFIGS, load_config, save_config, to_dict
from a2catvn_jax.errors import Interrupted, UserError
from a2catvn_jax.run.checkpoint import CONFIG_FILE, Checkpointer, config_differences, read_run_config
from a2catvn_jax.run.evaluation import evaluate_baseline, evaluate_sets, to_json
from a2catvn_jax.run.logger import read_jsonl
from a2catvn_jax.run.plots import smooth
from a2catvn_jax.run.pretraining import PRETRAINED_DIR, pretrain
from a2catvn_jax.run.training import train
from a2catvn_jax.run.workers import run_pool

SCALES = ("cpu", "paper")
DEFAULT_SEEDS = (0, 1, 2, 3, 4)
DEFAULT_ROOT = Path("runs/experiments")
DEFAULT_STORE = Path("docs/experiments/runs")
SMOOTH_FRACTION = 0.1  # curves are running means over this fraction of a run's log rows
FINAL_FRACTION = 0.1  # "final" training success: the mean over this last fraction of the rows
CONFIDENCE = 0.95  # of the t-intervals
EVAL_SETS = {"train": "training houses", "new-targets": "new targets", "held-out": "held-out houses"}
BASELINE_LABELS = {"random": "uniformly random policy", "oracle": "shortest-path oracle"}
# The training-log columns a stored run keeps (the curves, the plots, the learning-rate
# and complexity schedules, the gradient norm); the full log stays in the work directory.
STORED_COLUMNS = ("update", "frames", "complexity", "episodes", "success_rate", "episode_length", "spl",
                  "episode_return", "grad_norm", "loss/total")
DONE = "done.json"
BASELINE_DIR = "baselines"

AUX_LOSSES = ("off_policy_critic", "pixel_control", "reward_prediction", "depth", "segmentation", "target_segmentation")
NO_VN = ("train.loss_weights.depth=0", "train.loss_weights.segmentation=0", "train.loss_weights.target_segmentation=0")
NO_RP = "train.loss_weights.reward_prediction=0"
NO_UNREAL = ("train.loss_weights.off_policy_critic=0", "train.loss_weights.pixel_control=0", NO_RP)
CLIP_40 = "train.max_grad_norm=40"  # above every gradient norm measured on the house task
BLIND = ("agent.blind=true",)
# The loss and replay settings of the authors' published code where they differ from the
# defaults (docs/method.md), and their network (configs/presets/authors_network.yaml; its
# convolutions padded, which the 32 px CPU tasks need).
AUTHORS_LOSSES = ("train.loss_weights.critic=1.0", "train.loss_weights.off_policy_critic=2.0",
                  "train.loss_weights.pixel_control=0.1", "train.reward_prediction_loss=sigmoid",
                  "train.reward_prediction_zero_fraction=0.3333", "train.reward_prediction_target=next_frame",
                  "train.pixel_control_reward=rgb", "train.replay_warmup=true", "train.timeout_bootstrap=false")
AUTHORS_NETWORK = ("agent.conv_channels=[32,32,64,32]", "agent.conv_kernels=[7,4,4,1]", "agent.conv_strides=[4,2,2,1]",
                   "agent.conv_padding=same", "agent.dense_size=512", "agent.core_size=512",
                   "agent.vision_heads=transposed", "agent.init=uniform_fan_in")


class ExperimentError(UserError, RuntimeError):
    """An experiment cannot run as asked."""


@dataclasses.dataclass(frozen=True)
class Variant:
    label: str
    overrides: tuple[str, ...] = ()
    pretrain: bool = False  # start from `python -m a2catvn_jax.pretrain` with the same configuration and seed


# Every experiment's control: the configured agent trained on images of zeros, so what it
# reaches needs no sight. Runs are named by their configuration, so the experiments on
# one task share its blind runs.
BLIND_CONTROL = Variant("blind A2CAT-VN", BLIND)


@dataclasses.dataclass(frozen=True)
class Experiment:
    name: str
    title: str
    config: str  # configs/<config>.yaml (paper) and configs/<config>_cpu.yaml (cpu)
    variants: tuple[Variant, ...]
    threshold: float = 0.9  # training success rate for "frames to threshold" at paper scale
    cpu_threshold: float = 0.5  # the same at CPU scale (short runs reach lower rates)
    evaluations: tuple[str, ...] = ("train", "new-targets", "held-out")
    paper: str = ""  # what the paper reports for this comparison
    cpu_only: bool = False  # one configuration, configs/<config>.yaml, a CPU task at both scales

    def threshold_at(self, scale: str) -> float:
        return self.cpu_threshold if scale == "cpu" else self.threshold

    def config_path(self, scale: str) -> Path:
        if scale not in SCALES:
            raise ExperimentError(f"scale must be one of {SCALES}, got {scale!r}")
        cpu = scale == "cpu" and not self.cpu_only
        return CONFIGS / (f"{self.config}_cpu.yaml" if cpu else f"{self.config}.yaml")


EXPERIMENTS = {e.name: e for e in (
    Experiment(
        "sight", "A2CAT-VN vs the same agent blind on the quickstart task", "quickstart",
        (Variant("A2CAT-VN"), BLIND_CONTROL),
        cpu_threshold=0.7, evaluations=("train",), cpu_only=True,
        paper="Not in the paper. The blind agent's network sees zero images: what it reaches needs no sight, "
              "so the gap between the two is what the images are used for.",
    ),
    Experiment(
        "aux", "A2CAT-VN vs A2C+UNREAL vs A2C, and a blind A2CAT-VN", "image_goals",
        (Variant("A2CAT-VN (pre-trained)", pretrain=True), Variant("A2CAT-VN"), Variant("A2C+UNREAL", NO_VN),
         Variant("A2C", NO_VN + NO_UNREAL), BLIND_CONTROL),
        paper="House3D, 16 houses: average episode length 200 after about 3M frames with the visual-navigation "
              "auxiliary tasks, about 8M without them (A2C+UNREAL); plain A2C is not shown. The blind agent (its "
              "network sees zero images) is a control: what it reaches needs no sight.",
    ),
    Experiment(
        "aux_quickstart", "A2CAT-VN vs A2C+UNREAL vs A2C on the quickstart task", "quickstart",
        (Variant("A2CAT-VN (pre-trained)", ("pretrain.dataset_size=4000", "pretrain.epochs=10"), pretrain=True),
         Variant("A2CAT-VN"), Variant("A2C+UNREAL", NO_VN), Variant("A2C", NO_VN + NO_UNREAL), BLIND_CONTROL),
        cpu_threshold=0.7, evaluations=("train",), cpu_only=True,
        paper="House3D, 16 houses: average episode length 200 after about 3M frames with the visual-navigation "
              "auxiliary tasks, about 8M without them (A2C+UNREAL); plain A2C is not shown. The A2CAT-VN runs are "
              "the sight experiment's, whose blind agent is the control for this task.",
    ),
    Experiment(
        "ablations", "A2CAT-VN without one auxiliary loss at a time", "image_goals",
        (Variant("A2CAT-VN"),) + tuple(
            Variant(f"without {loss.replace('_', ' ')}", (f"train.loss_weights.{loss}=0",)) for loss in AUX_LOSSES)
        + (Variant("A2C+UNREAL", NO_VN), BLIND_CONTROL),
        paper="The paper compares A2CAT-VN with A2C+UNREAL (all three visual-navigation losses removed together) "
              "and reports no leave-one-out ablation.",
    ),
    Experiment(
        "aux_without_rp", "with reward prediction off: A2CAT-VN vs A2C+UNREAL vs A2C", "image_goals",
        (Variant("A2CAT-VN without reward prediction", (NO_RP,)),
         Variant("A2C+UNREAL without reward prediction", NO_VN + (NO_RP,)), Variant("A2C", NO_VN + NO_UNREAL),
         BLIND_CONTROL),
        paper="Its House3D comparison (with and without the visual-navigation losses), here with the "
              "reward-prediction loss off in both, the loss whose gradient dominates the shared layers at the "
              "defaults (docs/results.md). Its A2CAT-VN runs are the ablations experiment's 'without reward "
              "prediction', its A2C and blind runs the aux experiment's.",
    ),
    Experiment(
        "ablations_quickstart", "A2CAT-VN without one auxiliary loss at a time, on the quickstart task", "quickstart",
        (Variant("A2CAT-VN"),) + tuple(
            Variant(f"without {loss.replace('_', ' ')}", (f"train.loss_weights.{loss}=0",)) for loss in AUX_LOSSES)
        + (Variant("A2C+UNREAL", NO_VN), BLIND_CONTROL),
        cpu_threshold=0.7, evaluations=("train",), cpu_only=True,
        paper="The paper compares A2CAT-VN with A2C+UNREAL (all three visual-navigation losses removed together) "
              "and reports no leave-one-out ablation. The A2CAT-VN runs are the sight experiment's.",
    ),
    Experiment(
        "authors", "this package's defaults vs the authors' loss settings and network, on the quickstart task",
        "quickstart",
        (Variant("A2CAT-VN"), Variant("A2CAT-VN, the authors' loss settings", AUTHORS_LOSSES),
         Variant("A2CAT-VN, the authors' network", AUTHORS_NETWORK), BLIND_CONTROL),
        cpu_threshold=0.7, evaluations=("train",), cpu_only=True,
        paper="Where the authors' code and this package differ (docs/method.md): their loss and replay settings "
              "(critic 1.0, off-policy critic 2.0, pixel control 0.1, sigmoid reward prediction on a third of "
              "zero-reward windows and the next frame's reward, RGB pixel-control rewards, a filled replay before "
              "the first update, no bootstrap at time-outs) and their network (padded here for 32 px). "
              "The A2CAT-VN runs are the sight experiment's.",
    ),
    Experiment(
        "memory", "LSTM vs frame stack", "maze",
        (Variant("LSTM"), Variant("frame stack", ("agent.memory=frame_stack",)), BLIND_CONTROL),
        cpu_threshold=0.7,
        paper="DeepMind Lab SeekAvoid, UNREAL auxiliary tasks: the LSTM clearly outperforms four stacked frames.",
    ),
    Experiment(
        "pretraining", "with vs without supervised pre-training", "image_goals",
        (Variant("no pre-training"), Variant("pre-trained", pretrain=True), BLIND_CONTROL),
        paper="Pre-training is part of the House3D run (2e4 images, 30 epochs of Adam); the paper reports no "
              "ablation of it and names its effect as future work.",
    ),
    Experiment(
        "curriculum", "with vs without the curriculum", "image_goals",
        (Variant("no curriculum", ("train.curriculum=false",)), Variant("curriculum", ("train.curriculum=true",)),
         BLIND_CONTROL),
        paper="The curriculum (complexity 0.3 to 1.0 between 5M and 10M frames) is part of the House3D run; "
              "the paper reports no ablation of it.",
    ),
    Experiment(
        "generalisation", "room-type goals over many houses (64 at CPU scale, a new one each episode; 16 at paper scale): training vs held-out houses", "house_rooms",
        (Variant("A2CAT-VN"), BLIND_CONTROL),
        paper="The paper leaves generalisation to unseen houses and unseen targets as future work.",
    ),
    Experiment(
        "navigation", "levers for navigating unseen houses (room-type goals over many houses)", "house_rooms",
        (Variant("A2CAT-VN"), Variant("A2CAT-VN, clip 40", (CLIP_40,)),
         Variant("A2CAT-VN without reward prediction", (NO_RP,)), BLIND_CONTROL),
        paper="Not in the paper. Each variant changes one setting that learned faster on the house task; "
              "the A2CAT-VN and blind runs are the generalisation experiment's.",
    ),
    Experiment(
        "clipping", "gradient-norm clipping with the auxiliary losses", "image_goals",
        (Variant("A2CAT-VN, clip 0.5"), Variant("A2CAT-VN, clip 40", (CLIP_40,)),
         Variant("A2C, clip 0.5", NO_VN + NO_UNREAL), BLIND_CONTROL),
        paper="Table I clips the global gradient norm at 0.5. The auxiliary losses add to that norm, so the clip "
              "also shrinks the actor-critic part of the step; the paper does not discuss this.",
    ),
    Experiment(
        "aux_clip40", "with the gradient-norm clip at 40: A2CAT-VN (pre-trained and not) vs A2C+UNREAL vs A2C",
        "image_goals",
        (Variant("A2CAT-VN (pre-trained), clip 40", (CLIP_40,), pretrain=True), Variant("A2CAT-VN, clip 40", (CLIP_40,)),
         Variant("A2C+UNREAL, clip 40", NO_VN + (CLIP_40,)), Variant("A2C", NO_VN + NO_UNREAL), BLIND_CONTROL),
        paper="Its House3D comparison (with and without the visual-navigation losses), here with every loss "
              "kept and the gradient-norm clip at 40, far above the logged gradient norms: at Table I's 0.5 the clip "
              "acts throughout training with reward prediction and slows learning on this task (the clipping "
              "experiment). Its "
              "A2CAT-VN, clip 40 runs are the clipping experiment's, its A2C and blind runs the aux experiment's.",
    ),
    Experiment(
        "aux_every", "the depth and segmentation losses on every rollout frame vs every 4th (train.aux_every)",
        "image_goals",
        (Variant("A2CAT-VN"), Variant("A2CAT-VN, vision losses every 4th frame", ("train.aux_every=4",)), BLIND_CONTROL),
        paper="The paper computes the depth and segmentation losses on every frame. Every 4th frame divides "
              "their memory and time by about 4 (what lets thousands of environments train in memory); this "
              "measures what it costs learning. The A2CAT-VN runs are the aux experiment's.",
    ),
    Experiment(
        "grid", "grid actions on small rooms: A2CAT-VN vs A2C", "grid",
        (Variant("A2CAT-VN"), Variant("A2C", NO_VN + NO_UNREAL), BLIND_CONTROL),
        cpu_threshold=0.7,
        paper="AI2-THOR, four scenes, grid actions: A2CAT-VN finds the optimal solution after about 5e5 frames.",
    ),
)}


# -- runs -----------------------------------------------------------------------------


def _hash(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:8]


def run_key(cfg, pretrain: bool) -> str:
    """8 hex digits naming a (configuration without its seed, pre-trained or not) pair.
    Every key of the configuration counts, so a run is reused only for exactly its
    configuration (a new configuration key renames all runs)."""
    data = to_dict(cfg)
    data.pop("seed")
    return _hash(json.dumps(data, sort_keys=True) + ("|pretrain" if pretrain else ""))


def env_key(cfg) -> str:
    """8 hex digits naming the environment section of a configuration (what a baseline depends on)."""
    return _hash(json.dumps(to_dict(cfg)["env"], sort_keys=True))


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


def _same_run(directory: Path, cfg, pretrain: bool) -> bool:
    """Whether the stored run in `directory` was trained with configuration `cfg` (its
    saved configuration read as the training code reads an older run's: keys added since
    take their default, or the value of `LEGACY_VALUES` that reproduces the old behaviour)."""
    try:
        variant = json.loads((directory / "variant.json").read_text())
        saved = read_run_config(directory)
    except (OSError, ValueError, UserError):
        return False
    return bool(variant.get("pretrain")) == pretrain and not config_differences(saved, cfg, ignore=())


def _stored_dir(base: Path, key: str, seed: int, cfg, pretrain: bool) -> Path:
    """Where the run (`base`: STORE/SCALE/CONFIG) is stored: BASE/KEY/seed_N, or the
    directory of a finished run under another key with the same configuration (a run
    stored before keys were added to the configuration); BASE/KEY/seed_N if none."""
    primary = base / key / f"seed_{seed}"
    if (primary / DONE).is_file():
        return primary
    for other in sorted(base.glob(f"*/seed_{seed}")):
        if other.parent.name not in (key, BASELINE_DIR) and (other / DONE).is_file() and _same_run(other, cfg, pretrain):
            return other
    return primary


def _unfinished_dir(base: Path, key: str, seed: int, cfg, pretrain: bool) -> Optional[Path]:
    """The work directory (`base`: ROOT/SCALE/CONFIG) of a run in progress under another
    key with the same configuration and at least one checkpoint (the furthest along), when
    BASE/KEY/seed_N has none: a run started before keys were added to the configuration
    resumes there."""
    if _saved_updates(base / key / f"seed_{seed}"):
        return None
    found = [(max(_saved_updates(other), default=-1), other) for other in sorted(base.glob(f"*/seed_{seed}"))
             if other.parent.name not in (key, BASELINE_DIR) and _same_run(other, cfg, pretrain)]
    found = [(updates, other) for updates, other in found if updates >= 0]
    return max(found, key=lambda f: f[0])[1] if found else None  # the one furthest along


def plan(exp: Experiment, scale: str, seeds: Sequence[int], root=DEFAULT_ROOT, overrides: Sequence[str] = (),
         store=DEFAULT_STORE) -> list[Run]:
    """The runs of `exp`: every variant with every seed, configurations checked. A run is
    named ROOT|STORE/SCALE/CONFIG/RUN_KEY/seed_N, or by the stored run of the same
    configuration under an older key, or (not stored yet) by the work directory of the
    same configuration in progress under an older key."""
    path = exp.config_path(scale)
    base = Path(store) / scale / exp.config
    runs = []
    for variant in exp.variants:
        key = run_key(load_config(path, [*overrides, *variant.overrides]), variant.pretrain)
        for seed in seeds:
            cfg = load_config(path, [*overrides, *variant.overrides, f"seed={seed}"])
            stored = _stored_dir(base, key, seed, cfg, variant.pretrain)
            if not (stored / DONE).is_file():
                unfinished = _unfinished_dir(Path(root) / scale / exp.config, key, seed, cfg, variant.pretrain)
                if unfinished is not None:
                    stored = base / unfinished.relative_to(Path(root) / scale / exp.config)
            runs.append(Run(variant, seed, cfg, Path(root) / stored.relative_to(store), stored))
    return runs


def stored_runs(exp: Experiment, scale: str, store=DEFAULT_STORE, overrides: Sequence[str] = ()) -> dict:
    """variant label -> {seed: its stored directory} for the finished runs in `store`."""
    base = Path(store) / scale / exp.config
    candidates = sorted({int(d.name[5:]) for d in base.glob("*/seed_*") if d.name[5:].isdigit() and (d / DONE).is_file()})
    out = {}
    for variant in exp.variants:
        out[variant.label] = {r.seed: r.stored for r in plan(dataclasses.replace(exp, variants=(variant,)),
                                                             scale, candidates, store=store, overrides=overrides)
                              if r.is_stored()}
    return out


def stored_seeds(exp: Experiment, scale: str, store=DEFAULT_STORE, overrides: Sequence[str] = ()) -> dict:
    """variant label -> the seeds stored (finished) for it, sorted."""
    return {label: sorted(runs) for label, runs in stored_runs(exp, scale, store, overrides).items()}


def _saved_updates(workdir: Path) -> list[int]:
    """The update counts of the checkpoints in `workdir` (none if it has no checkpoint yet)."""
    if not (workdir / "checkpoints").is_dir():
        return []
    ckpt = Checkpointer(workdir, create=False)
    try:
        return ckpt.steps()
    finally:
        ckpt.close()


def has_final_checkpoint(run: Run) -> bool:
    return max(_saved_updates(run.workdir), default=0) >= total_updates(run.cfg)


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


def training_seconds(run: Run) -> Optional[float]:
    """Wall time the run took to train (pre-training and compilation included), if recorded."""
    for directory in (run.stored, run.workdir):
        timing = directory / "experiment_time.json"
        if timing.exists():
            return json.loads(timing.read_text())["seconds"]
    return None


# -- the store --------------------------------------------------------------------------


def _round(value, digits: int = 4):
    """Floats to `digits` significant digits (what a stored file keeps); anything else as is."""
    if isinstance(value, float) and math.isfinite(value) and value != 0.0:
        return float(f"{value:.{digits}g}")
    if isinstance(value, list):
        return [_round(v, digits) for v in value]
    if isinstance(value, dict):
        return {k: _round(v, digits) for k, v in value.items()}
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
    return [{k: _round(row[k]) for k in STORED_COLUMNS if k in row} for row in _without_repeats(rows)]


def _write_jsonl(path: Path, rows: list[dict]) -> None:
    path.write_text("".join(json.dumps(row, allow_nan=True) + "\n" for row in rows))


def eval_name(houses: str, policy: str, episodes: int) -> str:
    return f"eval_{houses}_{policy}_{episodes}.json"


def _stored_result(result: dict) -> dict:
    """An evaluation result as stored: no machine path, floats rounded."""
    return _round({k: v for k, v in result.items() if k not in ("workdir", "video")})


def git_commit() -> Optional[dict]:
    """The commit of the package's checkout and whether tracked files differ from it (None outside git)."""
    here = Path(__file__).resolve().parent
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=30)
        if sha.returncode:
            return None
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                                capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return {"commit": sha.stdout.strip(), "dirty": bool(status.stdout.strip()) if status.returncode == 0 else None}


def store_run(run: Run, evals: dict, episodes: int) -> None:
    """Copy the small results of the finished, evaluated `run` (houses -> result) to its
    stored directory; done.json goes last, so a copy that was interrupted is not taken
    for a finished run."""
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
    pre = run.workdir / "pretrain" / "pretrain_metrics.jsonl"
    if pre.is_file():
        _write_jsonl(d / "pretrain_metrics.jsonl", [_round(r) for r in read_jsonl(pre)])
    for houses, result in evals.items():
        if result is not None:
            (d / eval_name(houses, result["policy"], episodes)).write_text(to_json(_stored_result(result)))
    seconds = training_seconds(run)
    if seconds is not None:
        (d / "experiment_time.json").write_text(json.dumps({"seconds": round(seconds, 1)}) + "\n")
    done = {"updates": total_updates(run.cfg), "frames": rows[-1]["frames"] if rows else None,
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "machine": machine(), "git": git_commit()}
    (d / DONE).write_text(json.dumps(done, indent=1) + "\n")


def done_record(run: Run) -> dict:
    return json.loads((run.stored / DONE).read_text())


def stored_log(run: Run) -> list[dict]:
    """The rows of the run's stored metrics.jsonl."""
    return read_jsonl(run.stored / "metrics.jsonl")


def evaluate_run(run: Run, houses: Sequence[str], episodes: int, policy: str = "sample", *,
                 skip_missing: bool = False, log: Callable[[str], None] = lambda _: None) -> dict:
    """houses -> the evaluation of the run's last checkpoint in those houses.

    Each result is read from the store, else from the work directory's cache; the
    missing ones are evaluated together from the final checkpoint (one restore, one
    compile for the sets of one shape), cached and, for a stored run, added to the
    store. Without that checkpoint: `ExperimentError`, or None for each missing set
    with `skip_missing`."""
    def cached(h):
        return run.workdir / f"experiment_eval_{h}_{policy}_{episodes}.json"

    results = {}
    updates = total_updates(run.cfg)
    for h in houses:
        for path in (run.stored / eval_name(h, policy, episodes), cached(h)):
            if path.is_file():
                result = json.loads(path.read_text())
                if result["step"] == updates:
                    results[h] = result
                    if path == cached(h) and run.is_stored():
                        (run.stored / eval_name(h, policy, episodes)).write_text(to_json(_stored_result(result)))
                    break
    missing = [h for h in houses if h not in results]
    if not missing:
        return results
    if not has_final_checkpoint(run):
        if skip_missing:
            log(f"skipped: {run.name} has no stored evaluation in {', '.join(missing)} with {episodes} episodes")
            return {**results, **{h: None for h in missing}}
        stored = sorted(p.name for p in run.stored.glob("eval_*.json"))
        raise ExperimentError(
            f"{run.name} ({run.stored}): no stored evaluation in {', '.join(missing)} houses with {policy} policy and "
            f"{episodes} episodes (stored: {', '.join(stored) or 'none'}), and its final checkpoint is not in "
            f"{run.workdir}; use the stored episode count, or pass --skip-missing")
    log(f"evaluating {run.name} in {', '.join(missing)}")
    fresh = evaluate_sets(run.workdir, episodes, houses=missing, policies=(policy,), log=lambda _: None)
    for h in missing:
        results[h] = fresh[(h, policy)]
        cached(h).write_text(to_json(results[h]))
        if run.is_stored():
            (run.stored / eval_name(h, policy, episodes)).write_text(to_json(_stored_result(results[h])))
    return results


def baselines(exp: Experiment, scale: str, cfg, houses: Sequence[str], episodes: int, store=DEFAULT_STORE,
              log: Callable[[str], None] = lambda _: None) -> dict:
    """policy -> houses -> the result of that baseline (`BASELINE_LABELS`) in the
    experiment's environment, cached in STORE/SCALE/CONFIG/baselines/."""
    directory = Path(store) / scale / exp.config / BASELINE_DIR
    out: dict = {}
    for policy in BASELINE_LABELS:
        out[policy] = {}
        for h in houses:
            path = directory / f"{policy}_{h}_{episodes}_{env_key(cfg)}.json"
            if not path.is_file():
                log(f"evaluating the {BASELINE_LABELS[policy]} in {EVAL_SETS[h]}")
                result = evaluate_baseline(cfg, episodes, houses=h, policy=policy, log=lambda _: None)
                directory.mkdir(parents=True, exist_ok=True)
                path.write_text(to_json(_stored_result(result)))
            out[policy][h] = json.loads(path.read_text())
    return out


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


def curves(rows: list[dict]) -> dict:
    """frames, and the smoothed success rate, episode length and SPL of a training log."""
    k = max(1, round(SMOOTH_FRACTION * len(rows)))
    frames = np.array([r["frames"] for r in rows], float)
    out = {"frames": frames}
    for key in ("success_rate", "episode_length", "spl"):
        out[key] = smooth(np.array([_number(r.get(key)) for r in rows], float), k)
    return out


def _number(value) -> float:
    return math.nan if value is None else float(value)


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


def frames_text(value: float) -> str:
    """0, 400k, 1.2M."""
    if value == 0:
        return "0"
    return f"{value / 1e6:.1f}M" if value >= 1e6 else f"{value / 1e3:.0f}k"


def format_frames(per_run: Sequence[Optional[float]], f_max: float) -> str:
    """Frames to threshold over runs: the mean and interval of the runs that reach it,
    and how many never do (e.g. `410k [350k, 470k], 4/5 reached; 1 not by 2.0M`)."""
    reached = [v for v in per_run if v is not None]
    n, k = len(per_run), len(reached)
    if k == 0:
        return f"0/{n} reached by {frames_text(f_max)}"
    text = f"{estimate(reached, 0.0, f_max).format(frames_text)}, {k}/{n} reached"
    return text if k == n else f"{text}; {n - k} not by {frames_text(f_max)}"


def summarise(exp: Experiment, runs: list[Run], evals: dict, baseline: dict, threshold: float) -> dict:
    """Per variant, from the stored runs: curves (mean and 95% t-band), frames to
    threshold, final training success and evaluation numbers, each per seed."""
    variants = {}
    first_frames = first_eval = None
    for variant in exp.variants:
        mine = [r for r in runs if r.variant == variant]
        logs = [stored_log(r) for r in mine]
        cs = [curves(rows) for rows in logs]
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
        entry["final_success"] = [final_success(rows) for rows in logs]
        entry["late_change"] = [late_change(rows) for rows in logs]
        entry["training_seconds"] = [training_seconds(r) for r in mine]
        entry["eval"] = {h: {m: [None if evals[(r.relative, h)] is None else evals[(r.relative, h)][m] for r in mine]
                             for m in ("success_rate", "spl")} for h in exp.evaluations}
        if first_eval is None:
            first_eval = entry["eval"]
        entry["welch_p_eval_success_vs_first"] = None if variant == exp.variants[0] else {
            h: welch_p(*([v for v in e[h]["success_rate"] if v is not None] for e in (first_eval, entry["eval"])))
            for h in exp.evaluations}
        done = [done_record(r) for r in mine]
        entry["trained"] = [{"date": d.get("date"), "machine": d.get("machine"), "git": d.get("git")} for d in done]
        variants[variant.label] = entry
    return {"experiment": exp.name, "title": exp.title, "threshold": threshold, "variants": variants,
            "baselines": baseline}


# -- outputs --------------------------------------------------------------------------


def _reference_houses(summary: dict) -> Optional[str]:
    """The house set whose baselines the curves show: the training houses when evaluated."""
    sets = [h for policy in summary["baselines"].values() for h in policy]
    return "train" if "train" in sets else (sets[0] if sets else None)


def plot(summary: dict, out, title: str) -> None:
    """Success rate and episode length against frames: the mean over seeds, shaded with
    its 95% t-band; horizontal lines for the threshold and the baselines."""
    rows = math.ceil((len(summary["variants"]) + 3) / 3)  # legend rows below the panels
    height = 3.4 + 0.17 * rows
    fig = Figure(figsize=(10, height))
    axes = fig.subplots(1, 2)
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
    axes[0].axhline(threshold, color="grey", linestyle=":", linewidth=1, label=f"threshold {threshold:g}")
    houses = _reference_houses(summary)
    for policy, style in (("random", "--"), ("oracle", "-.")):
        result = summary["baselines"].get(policy, {}).get(houses)
        if result is not None:
            name = f"{BASELINE_LABELS[policy]} ({EVAL_SETS[houses]})"
            axes[0].axhline(result["success_rate"], color="black", linestyle=style, linewidth=1, label=name)
            axes[1].axhline(result["episode_length"], color="black", linestyle=style, linewidth=1)
    axes[0].set_ylim(0, 1.02)
    axes[1].set_ylim(0, summary["max_episode_steps"] * 1.02)
    for ax, name in zip(axes, ("training success rate", "training episode length")):
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


def format_estimate(values, lo: float = 0.0, hi: float = 1.0, fmt: Callable[[float], str] = "{:.2f}".format) -> str:
    """`0.62 [0.55, 0.69]` over the values present; `(n=k)` when some are missing; – when none is."""
    est = estimate(values, lo, hi)
    if est is None:
        return "–"
    return est.format(fmt) + ("" if est.n == len(values) else f" (n={est.n})")


def table(summary: dict, evaluations: Sequence[str]) -> str:
    """The markdown table of a summary: per variant, the mean over seeds and its 95%
    t-interval; then the baselines' evaluation numbers."""
    head = ["variant", f"frames to success {summary['threshold']:g}", "final training success",
            f"change over the last {FINAL_FRACTION:.0%}"]
    for h in evaluations:
        head += [f"success, {EVAL_SETS[h]}", f"SPL, {EVAL_SETS[h]}"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label, v in summary["variants"].items():
        cells = [label, format_frames(v["frames_to_threshold"], v["frames_max"]), format_estimate(v["final_success"]),
                 format_estimate(v["late_change"], -1.0, 1.0, "{:+.2f}".format)]
        for h in evaluations:
            cells += [format_estimate(v["eval"][h]["success_rate"]), format_estimate(v["eval"][h]["spl"])]
        lines.append("| " + " | ".join(cells) + " |")
    for policy, label in BASELINE_LABELS.items():
        cells = [label, "–", "–", "–"]
        for h in evaluations:
            r = summary["baselines"].get(policy, {}).get(h)
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


def seeds_text(seeds: Sequence[int]) -> str:
    seeds = sorted(seeds)
    if len(seeds) > 2 and seeds == list(range(seeds[0], seeds[-1] + 1)):
        return f"{seeds[0]}–{seeds[-1]}"
    return ", ".join(map(str, seeds))


def _provenance(summary: dict) -> str:
    """Where, when and from which commit the runs were trained (from their done.json)."""
    trained = [t for v in summary["variants"].values() for t in v["trained"]]
    machines = Counter(t["machine"] or "unknown" for t in trained)
    dates = sorted(t["date"][:10] for t in trained if t["date"])
    commits = Counter((t["git"] or {}).get("commit", "unknown")[:10] + ("+changes" if (t["git"] or {}).get("dirty") else "")
                      for t in trained)
    text = "Trained on " + "; ".join(f"{m} ({k} run{'s' if k > 1 else ''})" for m, k in machines.most_common())
    if dates:
        text += f", {dates[0]}" + (f" to {dates[-1]}" if dates[-1] != dates[0] else "")
    return text + "; code: " + ", ".join(f"{c} ({k})" for c, k in commits.most_common()) + "."


def _mean_minutes(seconds: Sequence[Optional[float]]) -> str:
    known = [s for s in seconds if s is not None]
    return f"{np.mean(known) / 60:.1f} min" if known else "not recorded"


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
        f"Configuration: `configs/{exp.config_path(scale).name}`; variants: "
        + "; ".join(f"{v.label}" + (f" (`{' '.join(v.overrides)}`)" if v.overrides else "")
                    + (" (pre-trained)" if v.pretrain and "pre-trained" not in v.label else "")
                    for v in exp.variants) + ".  ",
        *([f"Not in this part-way report, no run stored yet: {'; '.join(summary['not_stored'])}.  "]
          if summary.get("not_stored") else []),
        f"Seeds: {seeds_line}. Evaluation: {summary['episodes']} "
        f"episodes per run and house set, sampled policy, complexity 1.  ",
        _provenance(summary) + " Mean training wall time per run: "
        + "; ".join(f"{label} {_mean_minutes(v['training_seconds'])}" for label, v in summary["variants"].items())
        + " (compilation and pre-training included).",
        "",
        f"![{exp.name}]({image})",
        "",
        table(summary, evaluations),
        "",
        ("One seed: each cell is that run's value, no interval" if max(map(len, seeds.values())) == 1 else
         "Each cell: the mean over the seeds and its 95% t-interval [low, high] (Student's t, n − 1 degrees of "
         "freedom, clipped to the possible range" + ("; a variant with one run: its value, no interval)" if n == 1
                                                     else ")"))
        + "; (n=k): only k runs have that number. "
        f"Frames to threshold: the first log row at which the training success rate, a running mean over "
        f"{SMOOTH_FRACTION:.0%} of the run, reaches {threshold:g}; the mean and interval are over the runs that reach "
        f"it, and the runs that never do are counted. Final training success: the last {FINAL_FRACTION:.0%} of the "
        f"run; its change: that minus the {FINAL_FRACTION:.0%} before it (above 0: still improving when the run "
        f"ended). Baselines, evaluated like the runs but with no training: a {BASELINE_LABELS['random']} and the "
        f"{BASELINE_LABELS['oracle']} (`env.oracle`)."
        + (" The blind variant (`agent.blind=true`) trains like the others on images of zeros: what it reaches "
           "needs no sight." if any("agent.blind=true" in v.overrides for v in exp.variants) else "")
        + f" Curves: the mean over seeds of the running mean, shaded with its 95% t-band; dotted: the threshold; "
        f"dashed and dash-dotted: the random policy's and the oracle's success rate and episode length in the "
        f"{EVAL_SETS.get(_reference_houses(summary), 'evaluated houses')}.",
    ]
    tests = [(label, v["welch_p_frames_vs_first"]) for label, v in summary["variants"].items()][1:]
    if tests and any(p is not None for _, p in tests):
        first = next(iter(summary["variants"]))
        lines += ["", f"Welch's t-test on frames to threshold against {first}, a run that never reaches it counted "
                      f"at the run's last frame: " + "; ".join(f"{label} p = {'–' if p is None else f'{p:.2g}'}"
                                                              for label, p in tests) + "."]
    first = next(iter(summary["variants"]))
    for h in evaluations:
        tests = [(label, (v.get("welch_p_eval_success_vs_first") or {}).get(h))
                 for label, v in summary["variants"].items()][1:]
        if tests and any(p is not None for _, p in tests):
            lines += ["", f"Welch's t-test on evaluation success ({EVAL_SETS[h]}) against {first}: "
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
                what = " ".join(v.overrides) or "as configured"
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


# -- the whole experiment ----------------------------------------------------------------


def _compilation_cache(directory: Path) -> None:
    """Keep compiled programs on disk: seeds of a variant (same shapes and scenes) compile once."""
    if jax.config.jax_compilation_cache_dir is None:
        jax.config.update("jax_compilation_cache_dir", str(directory.absolute()))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def _train_in_processes(exp: Experiment, scale: str, runs: list[Run], jobs: int, *, episodes: int, root, docs,
                        store, overrides: Sequence[str], log: Callable[[str], None]) -> None:
    """Train, evaluate and store `runs`, `jobs` at a time, each in its own process on its
    share of the cores (`workers.run_pool`); raises `ExperimentError` naming the runs
    that failed and their logs."""
    def command(run: Run) -> list[str]:
        return [sys.executable, "-m", "a2catvn_jax.experiments", exp.name, "--scale", scale,
                "--seeds", str(run.seed), "--train-only", run.variant.label, "--episodes", str(episodes),
                "--root", str(root), "--store", str(store), "--docs", str(docs), "--no-report",
                *(["--set", *overrides] if overrides else [])]

    logs = [run.workdir / "train.log" for run in runs]
    t0 = time.perf_counter()

    def started(i, cores):
        log(f"started {runs[i].name} on core(s) {','.join(map(str, cores))}; log: {logs[i]}")

    def ended(i, code):
        minutes = (time.perf_counter() - t0) / 60
        state = "stored" if code == 0 and runs[i].is_stored() else f"FAILED (exit status {code})"
        log(f"{state}: {runs[i].name} ({minutes:.1f} min after the start)")

    log(f"training {len(runs)} run(s), {jobs} at a time, each in its own process")
    codes = run_pool([command(run) for run in runs], jobs, logs, on_start=started, on_end=ended)
    failed = [f"{run.name} (log: {path})" for run, path, code in zip(runs, logs, codes)
              if code != 0 or not run.is_stored()]
    if failed:
        raise ExperimentError(f"{len(failed)} of {len(runs)} run(s) failed: " + "; ".join(failed))


def run_experiment(exp: Experiment, *, scale: str = "cpu", seeds: Sequence[int] = DEFAULT_SEEDS, episodes: int = 100,
                   root=DEFAULT_ROOT, docs="docs", store=None, overrides: Sequence[str] = (), command: str = "",
                   threshold: Optional[float] = None, skip_missing: bool = False, compilation_cache: bool = True,
                   train_only: Optional[Sequence[str]] = None, jobs: int = 1, report: bool = True,
                   stored_only: bool = False, log: Optional[Callable[[str], None]] = None) -> dict:
    """Train, evaluate, store and report `exp`; returns its summary (also written as JSON).

    Runs stored in `store` (default DOCS/experiments/runs) are not trained again, and
    their curves and evaluations come from the store; the others are trained in `root`,
    evaluated and stored. `threshold` replaces the experiment's success-rate threshold
    at this scale; `skip_missing` leaves out evaluations a stored run lacks and cannot
    make here (no checkpoint) instead of raising `ExperimentError`; `compilation_cache`
    keeps compiled programs in ROOT/.jax_cache (a process-wide JAX setting).
    `train_only` (variant labels) trains only those variants' runs; while runs of the
    others are neither stored nor trained, nothing is reported and the summary is
    {"experiment": name, "pending": [run names]}: a long experiment can be trained a
    variant at a time, across sittings and machines, through the store.

    Runs train seed by seed (every variant of seed 0, then of seed 1, ...), so an
    experiment stopped part-way leaves comparable seeds behind. `stored_only` trains
    nothing and reports the stored runs among `seeds`, however many each variant has
    (a look at a long experiment part-way); a variant with none stored yet is left out and
    named in the section (the first variant, the reference, needs one).

    `jobs` > 1 trains that many runs at once, each in a process of its own pinned to its
    share of the CPU cores (`workers.run_pool`; on a CPU with few cores the runs finish
    sooner in all, docs/benchmarks.md; on one GPU keep 1); each process trains,
    evaluates and stores one run and writes its output to `train.log` in the run's
    directory under ROOT. `report=False` stops after the training (what those processes
    do).
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
    docs = Path(docs)
    store = docs / "experiments" / "runs" if store is None else Path(store)
    labels = [v.label for v in exp.variants]
    unknown = [label for label in train_only or () if label not in labels]
    if unknown:
        raise ExperimentError(f"{exp.name} has no variant {', '.join(map(repr, unknown))}; its variants: "
                              + ", ".join(map(repr, labels)))
    t0 = time.perf_counter()
    runs = plan(exp, scale, seeds, root, overrides, store)
    not_stored = []  # variants a part-way report leaves out: none of their runs is stored yet
    if stored_only:
        runs = [r for r in runs if r.is_stored()]
        not_stored = [v.label for v in exp.variants if not any(r.variant == v for r in runs)]
        if exp.variants[0].label in not_stored:  # the reference every other variant is tested against
            raise ExperimentError(f"{exp.name}: no run of {exp.variants[0].label!r} (the variant the others are "
                                  f"compared with) is stored in {store}")
        if not_stored:
            log(f"{exp.name}: left out of this part-way report, none of their runs stored yet: "
                + ", ".join(map(repr, not_stored)))
            exp = dataclasses.replace(exp, variants=tuple(v for v in exp.variants if v.label not in not_stored))
    if compilation_cache:
        _compilation_cache(Path(root) / ".jax_cache")
    stored = sum(r.is_stored() for r in runs)
    log(f"{exp.name}: {len(runs)} runs, {stored} stored in {store}, {len(runs) - stored} to train or finish")
    to_train = {}  # work directory -> run: variants with the same configuration share one run
    for run in sorted(runs, key=lambda r: r.seed):  # seed by seed: a stopped experiment leaves whole seeds
        if not run.is_stored() and (train_only is None or run.variant.label in train_only):
            to_train.setdefault(run.workdir, run)
    if jobs > 1 and to_train:
        _train_in_processes(exp, scale, list(to_train.values()), jobs, episodes=episodes, root=root, docs=docs,
                            store=store, overrides=overrides, log=log)
    for i, run in sorted(enumerate(runs), key=lambda ir: ir[1].seed):
        if run.is_stored() or run.workdir not in to_train:
            continue
        log(f"[{i + 1}/{len(runs)}] {run.name}")
        seconds = train_run(run, log)
        if seconds:
            log(f"  trained in {seconds / 60:.1f} min")
        results = evaluate_run(run, exp.evaluations, episodes, log=log)
        store_run(run, results, episodes)
        log(f"  stored in {run.stored}")
    if not report:
        return {"experiment": exp.name, "trained": [run.name for run in runs if run.is_stored()]}
    pending = [run.name for run in runs if not run.is_stored()]
    if pending:
        log(f"not reported: {len(pending)} run(s) neither stored nor trained now: {', '.join(pending)}")
        return {"experiment": exp.name, "pending": pending}
    evals = {}
    for run in runs:
        for houses, result in evaluate_run(run, exp.evaluations, episodes, skip_missing=skip_missing, log=log).items():
            evals[(run.relative, houses)] = result
    base_cfg = load_config(exp.config_path(scale), overrides)
    baseline = baselines(exp, scale, base_cfg, exp.evaluations, episodes, store, log)
    summary = summarise(exp, runs, evals, baseline, threshold)
    summary.update(scale=scale, episodes=episodes, max_episode_steps=runs[0].cfg.env.max_episode_steps,
                   overrides=list(overrides), command=command, not_stored=not_stored)
    out_json = store / scale / f"{exp.name}.json"
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(summary, indent=1) + "\n")
    image = docs / "experiments" / f"{exp.name}_{scale}.png"
    plot(summary, image, f"{exp.title} ({scale} scale, configs/{exp.config_path(scale).name})")
    write_section(docs / "results.md", exp, scale,
                  section(exp, scale, summary, command, image.relative_to(docs).as_posix()))
    log(f"wrote {image}, {out_json} and its section of {docs / 'results.md'} in {time.perf_counter() - t0:.0f} s")
    log(table(summary, exp.evaluations))
    return summary
