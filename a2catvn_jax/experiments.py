"""Comparisons of the method's variants: train with several seeds, evaluate, store, plot, tabulate.

    python -m a2catvn_jax.experiments NAME [--scale cpu|paper] [--seeds 0 1 2 3 4 | --stored-seeds | --all-stored]
        [--episodes 500] [--threshold T] [--root runs/experiments] [--store results]
        [--docs docs] [--skip-missing | --no-evaluate] [--jobs N] [--set KEY=VALUE ...]
    python -m a2catvn_jax.experiments NAME --stored-seeds --no-evaluate [--scale ...] [--store DIR] [--docs DIR]
    python -m a2catvn_jax.experiments NAME --plan [--seeds ...] [--root DIR] [--store DIR] [--set KEY=VALUE ...]
    python -m a2catvn_jax.experiments --list [NAME ...] [--scale cpu|paper] [--store DIR]
    python -m a2catvn_jax.experiments --compare EXPERIMENT:LABEL EXPERIMENT:LABEL [...] [--scale cpu|paper]
        [--store DIR]

Experiments (`EXPERIMENTS`):
  sight           A2CAT-VN vs the same agent blind on the quickstart task (configs/quickstart.yaml)
  aux             A2CAT-VN (pre-trained and not) vs A2C+UNREAL vs plain A2C, and a blind A2CAT-VN
  ablations       A2CAT-VN without one auxiliary loss at a time, and without all three visual-navigation ones
  ablations_quickstart  the same on the quickstart task (configs/quickstart.yaml)
  memory          LSTM vs frame stack (mazes, UNREAL auxiliary tasks)
  pretraining     with vs without supervised pre-training
  curriculum      with vs without the complexity curriculum
  generalisation  room-type goals over 64 houses (16 at paper scale), A2CAT-VN and blind; held-out houses and new targets
  navigation      room-type goals over many houses, one lever at a time: the clip at 40, no reward prediction,
                  256 houses, new houses every 200k frames, 256 houses for 20M frames; and blind
  navigation_preset  configs/presets/navigation.yaml against Table I's settings, blind, target-blind and
                  observation-blind
  declared_success  the preset, its target-blind control and the blind agent where success must be declared
                  (env.stop_action)
  batch           B 16 against B 64 and 256 with Table I's settings and with LAMB and a sqrt-scaled learning rate
  clipping        A2CAT-VN with the gradient-norm clip of Table I (0.5) vs 40, and A2C
  grid            the grid action set on small rooms (A2CAT-VN vs A2C)
  aux_every       the depth and segmentation losses on every frame vs every 4th (train.aux_every)
  aux_clip40      aux's comparison with the gradient-norm clip at 40 (every loss kept)

Every experiment also has the blind control (`BLIND_CONTROL`): the configured agent
trained on images of zeros (`agent.blind=true`), so every table shows what needs no
sight beside the random policy and the oracle. Experiments on one task share its blind
runs.

Each experiment names a configuration of `configs/`: `NAME_cpu.yaml` at `--scale cpu`
(minutes per run on a laptop CPU), `NAME.yaml` at `--scale paper` (the paper's sizes,
for a GPU). Every variant is trained once per seed (`seed=S`; the houses stay the same)
under its run key, a hash of the configuration's values that differ from the defaults
(`study.store.run_key`: a configuration key added with its default renames no run), so a
variant shared by two experiments (e.g. A2CAT-VN in `aux` and `ablations`) is trained
once. Pre-trained variants first run `pretrain` with the same seed. Each run is
evaluated with the sampled policy and with its argmax (greedy) in its training houses,
with new targets in them and in held-out houses (`evaluate --houses`), `--episodes`
episodes each (default 500) with the evaluation seed 1000 + the run's seed; a uniformly
random policy and the shortest-path oracle, which need no training, are evaluated in the
same houses with seed 999, and so on room-type goals is the goal-blind tour of the rooms
(`env.tour`: knows the map, not the goal).

Runs as data: a finished, evaluated run is copied to the store (default `results/`),
`STORE/SCALE/CONFIG/RUN_KEY/seed_N/` (config.yaml, variant.json, metrics.jsonl with the
columns the curves use, the evaluation JSONs, experiment_time.json and done.json:
updates, frames, date, machine, git commit); checkpoints and TensorBoard files stay in
ROOT. Commit the store: a stored run is never trained again, and the curves and tables
are made from the store, so on a fresh clone `python -m a2catvn_jax.experiments NAME`
re-plots and re-tabulates without training, and more `--seeds` train only the missing
ones. `--stored-seeds` uses the seeds stored for every variant and trains nothing;
`--all-stored` reports every stored run, however many seeds each variant has (a look at
an experiment part-way; a variant with none stored yet is left out and named), and
trains nothing. `--jobs N` trains N runs at once, each in its own process pinned to its
share of the CPU cores (its log in `train.log` in the run's directory under ROOT): on a
CPU with few cores a small run leaves cores idle, so runs side by side finish sooner in
all (docs/benchmarks.md); on one GPU keep 1. An evaluation a stored run lacks (another
`--episodes` or seed, the greedy policy) needs that run's checkpoint in ROOT; without it
the command stops with an error naming the run, unless `--skip-missing` reports the
stored evaluation of that run, house set and policy with the most episodes instead (or
leaves the number out when none is stored); the section says which episodes and seeds
each number rests on. `--no-evaluate` trains and evaluates nothing, runs or baselines,
and reports the store so: `NAME --stored-seeds --no-evaluate` re-tabulates an
experiment from the store alone. `--list` shows
how many seeds of each variant are stored. `--compare` sets variants of different
experiments side by side from their stored reports (`study.compare`: frames to
threshold, final and evaluation success, the logged gradient norms against each run's
clip, and Welch's tests against the first variant named); it trains nothing.

Outputs: `DOCS/experiments/NAME_SCALE.png` (training success rate and episode length
against frames: the mean over seeds, shaded with its 95% t-band; the threshold and the
baselines as horizontal lines), `STORE/SCALE/NAME.json` (every number, per seed), and
a section of `DOCS/results.md` between the markers `<!-- experiment NAME SCALE -->`
and `<!-- end experiment NAME SCALE -->` (rewritten on each run; text outside the
markers is kept) with the command, where and when the runs were trained, the
evaluations each number rests on, a table of means over seeds with 95% t-intervals:
frames until the smoothed training success rate first reaches the experiment's
threshold (and how many runs never do), its Kaplan-Meier restricted mean (runs that never
reach it censored at their last frame), final training success, evaluation success and
SPL, and the baselines' rows; a table of evaluation success with both policies, over
seeds (t-interval) and over all episodes pooled (Wilson's interval); Welch's and
log-rank tests against the first variant.
"""

from __future__ import annotations

import argparse
import sys

from a2catvn_jax import cli
from a2catvn_jax.config import ConfigError
from a2catvn_jax.errors import Interrupted
from a2catvn_jax.study import compare, report, runner, store
from a2catvn_jax.study.registry import EXPERIMENTS, SCALES, ExperimentError


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m a2catvn_jax.experiments", description=__doc__.split("\n\n")[0])
    parser.add_argument("name", nargs="*", help="experiment: " + ", ".join(EXPERIMENTS))
    parser.add_argument("--list", action="store_true",
                        help="list the experiments (or the NAMEs), their variants and how many seeds of each are stored")
    parser.add_argument("--compare", nargs="+", metavar="EXPERIMENT:LABEL", default=None,
                        help="set these variants of stored reports side by side and test each against the first "
                             "(e.g. 'aux:A2C+UNREAL' 'aux_clip40:A2C+UNREAL, clip 40'); trains nothing")
    parser.add_argument("--scale", choices=SCALES, default=None, help="default: cpu (--list: both)")
    seeds = parser.add_mutually_exclusive_group()
    seeds.add_argument("--seeds", type=int, nargs="+", default=list(runner.DEFAULT_SEEDS),
                       help=f"default: {' '.join(map(str, runner.DEFAULT_SEEDS))}")
    seeds.add_argument("--stored-seeds", action="store_true",
                       help="the seeds stored for every variant; trains nothing")
    seeds.add_argument("--all-stored", action="store_true",
                       help="every stored run, however many seeds each variant has (a part-way report; "
                            "variants with none stored are left out); trains nothing")
    parser.add_argument("--episodes", type=int, default=runner.DEFAULT_EPISODES,
                        help="evaluation episodes per run, house set and policy (default: %(default)s)")
    parser.add_argument("--threshold", type=float, default=None,
                        help="training success rate for 'frames to threshold' (default: the experiment's, per scale)")
    parser.add_argument("--root", default=str(store.DEFAULT_ROOT),
                        help="where the runs train (checkpoints, TensorBoard)")
    parser.add_argument("--store", default=str(store.DEFAULT_STORE),
                        help="where finished runs are stored, to commit (default: %(default)s)")
    parser.add_argument("--docs", default="docs", help="where results.md and the plots go")
    evaluations = parser.add_mutually_exclusive_group()
    evaluations.add_argument("--skip-missing", action="store_true",
                             help="an evaluation a stored run lacks and whose checkpoint is not here: report the "
                                  "stored one with the most episodes instead (the section says so), or leave it out")
    evaluations.add_argument("--no-evaluate", action="store_true",
                             help="train and evaluate nothing (runs or baselines): report what the store holds, "
                                  "falling back as --skip-missing does")
    parser.add_argument("--train-only", nargs="+", metavar="LABEL", default=None,
                        help="train only these variants (labels as --list shows them); the report waits until "
                             "every run is stored")
    parser.add_argument("--jobs", type=int, default=1,
                        help="train this many runs at once, each in its own process on its share of the CPU cores "
                             "(faster in all on a CPU with few cores; on one GPU keep 1)")
    parser.add_argument("--plan", action="store_true",
                        help="print one self-contained command per unfinished run (for a SLURM job array or any "
                             "scheduler: each stores its run in --store); trains nothing")
    parser.add_argument("--no-report", action="store_true", help=argparse.SUPPRESS)  # what --jobs' processes run
    cli.add_config_args(parser, config=False,
                        help="configuration changes applied to every variant (they change the runs' names)")
    args = parser.parse_args(argv)
    unknown = [n for n in args.name if n not in EXPERIMENTS]
    if unknown:
        parser.error(f"unknown experiment {unknown[0]!r}; choose one of {', '.join(EXPERIMENTS)}")
    if args.compare is not None:
        given = [option for option, used in (
            ("NAME", args.name), ("--list", args.list), ("--seeds", args.seeds != list(runner.DEFAULT_SEEDS)),
            ("--stored-seeds", args.stored_seeds), ("--all-stored", args.all_stored),
            ("--episodes", args.episodes != runner.DEFAULT_EPISODES), ("--threshold", args.threshold is not None),
            ("--train-only", args.train_only is not None), ("--skip-missing", args.skip_missing),
            ("--no-evaluate", args.no_evaluate), ("--jobs", args.jobs != 1), ("--set", cli.overrides_of(args)))
            if used]
        if given:
            parser.error(f"--compare reads the stored reports as they are; it takes no {', '.join(given)} "
                         "(only EXPERIMENT:LABEL arguments, --scale, --store and --docs)")
        with cli.errors(parser, code=2, kinds=(compare.CompareError, ValueError)):
            print(compare.compare(args.compare, args.scale or "cpu", args.store))
        return
    if args.list:
        with cli.errors(parser, code=2, kinds=(ConfigError, ExperimentError, ValueError)):
            print(report.listing(args.store, [args.scale] if args.scale else SCALES, args.name, cli.overrides_of(args)))
        return
    if len(args.name) != 1:
        parser.error("name one experiment (or --list)")
    if args.jobs < 1:
        parser.error(f"--jobs must be >= 1, got {args.jobs}")
    exp = EXPERIMENTS[args.name[0]]
    scale = args.scale or "cpu"
    command = "python -m a2catvn_jax.experiments " + " ".join(argv if argv is not None else sys.argv[1:])
    with cli.errors(parser, code=1), cli.errors(parser, code=2, kinds=(ConfigError, ExperimentError, ValueError)), \
            cli.errors(parser, code=130, kinds=(Interrupted,)):
        run_seeds = args.seeds
        if args.stored_seeds or args.all_stored:
            stored = store.stored_seeds(exp, scale, args.store, cli.overrides_of(args))
            combine = set.intersection if args.stored_seeds else set.union
            run_seeds = sorted(combine(*(set(s) for s in stored.values())))
            if not run_seeds:
                raise ExperimentError(f"{exp.name}: no seed is stored for every variant in {args.store} ("
                                      + "; ".join(f"{label}: {len(s)}" for label, s in stored.items()) + ")"
                                      if args.stored_seeds else f"{exp.name}: no run is stored in {args.store}")
        try:
            opts = runner.Options(scale=scale, seeds=run_seeds, episodes=args.episodes, root=args.root,
                                  docs=args.docs, store=args.store, overrides=cli.overrides_of(args),
                                  command=command.strip(), threshold=args.threshold, skip_missing=args.skip_missing,
                                  train_only=args.train_only, jobs=args.jobs, report=not args.no_report,
                                  stored_only=args.all_stored, evaluate=not args.no_evaluate)
            if args.plan:
                print("\n".join(runner.plan_commands(exp, opts)))
                return
            runner.run_experiment(exp, opts)
        except KeyboardInterrupt:  # a second Ctrl-C while a run trains in this process, or one while none does
            parser.exit(130, "aborted: the run in training keeps only its last checkpoint; "
                             "the same command resumes each unfinished run from its last checkpoint\n")


if __name__ == "__main__":
    cli.run_stoppable(main)
