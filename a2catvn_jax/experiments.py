"""Comparisons of the method's variants: train with several seeds, evaluate, plot, tabulate.

    python -m a2catvn_jax.experiments NAME [--scale cpu|paper] [--seeds 0 1] [--episodes 100]
        [--root runs/experiments] [--docs docs] [--set KEY=VALUE ...]
    python -m a2catvn_jax.experiments --list

Experiments (`EXPERIMENTS`):
  aux             A2CAT-VN vs A2C+UNREAL vs plain A2C (image goals in one house)
  memory          LSTM vs frame stack (mazes, UNREAL auxiliary tasks)
  pretraining     with vs without supervised pre-training (image goals in one house)
  curriculum      with vs without the complexity curriculum (image goals in one house)
  generalisation  room-type goals over 16 houses; held-out houses and new targets
  clipping        A2CAT-VN with the gradient-norm clip of Table I (0.5) vs 40, and A2C
  grid            the grid action set on small rooms (A2CAT-VN vs A2C)

Each experiment names a configuration of `configs/`: `NAME_cpu.yaml` at `--scale cpu`
(minutes per run on a laptop CPU), `NAME.yaml` at `--scale paper` (the paper's sizes,
for a GPU). Every variant is trained once per seed (`seed=S`; the houses stay the same)
in a work directory named by the hash of its configuration, so a variant shared by two
experiments (e.g. A2CAT-VN in `aux`, the baseline of `curriculum`) is trained once, and
an interrupted experiment resumes: finished runs are kept, unfinished ones continue
from their last checkpoint. Pre-trained variants first run `pretrain` with the same
seed. Each run is evaluated with the sampled policy in its training houses, with new
targets in them and in held-out houses (`evaluate --houses`), and a uniformly random
policy gives the baseline.

Outputs: `DOCS/experiments/NAME_SCALE.png` (training success rate and episode length
against frames: the mean over seeds, shaded ± one standard error), `ROOT/SCALE/NAME.json`
(every number, 95% t-intervals of the curves included), and a section of `DOCS/results.md` between the markers
`<!-- experiment NAME SCALE -->` and `<!-- end experiment NAME SCALE -->` (rewritten on
each run; text outside the markers is kept) with the command, machine, date, wall time
and a table: frames until the smoothed training success rate first reaches the
experiment's threshold, final training success, and evaluation success and SPL.
"""

from __future__ import annotations

import argparse
import sys

from a2catvn_jax import cli
from a2catvn_jax.config import ConfigError
from a2catvn_jax.run.experiments import EXPERIMENTS, SCALES, ExperimentError, run_experiment


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m a2catvn_jax.experiments", description=__doc__.split("\n\n")[0])
    parser.add_argument("name", nargs="?", help="experiment: " + ", ".join(EXPERIMENTS))
    parser.add_argument("--list", action="store_true", help="list the experiments and their variants")
    parser.add_argument("--scale", choices=SCALES, default="cpu")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--episodes", type=int, default=100, help="evaluation episodes per run and set")
    parser.add_argument("--threshold", type=float, default=None,
                        help="training success rate for 'frames to threshold' (default: the experiment's, per scale)")
    parser.add_argument("--root", default="runs/experiments", help="where the runs go")
    parser.add_argument("--docs", default="docs", help="where results.md and the plots go")
    cli.add_config_args(parser, config=False,
                        help="configuration changes applied to every variant (they change the runs' names)")
    args = parser.parse_args(argv)
    if args.list:
        for exp in EXPERIMENTS.values():
            print(f"{exp.name}: {exp.title} (configs/{exp.config}[_cpu].yaml; success threshold "
                  f"{exp.threshold:g}, {exp.cpu_threshold:g} at CPU scale)")
            for v in exp.variants:
                print(f"  {v.label}: {' '.join(v.overrides) or 'as configured'}{' + pre-training' if v.pretrain else ''}")
        return
    if args.name is None:
        parser.error("name an experiment (or --list)")
    if args.name not in EXPERIMENTS:
        parser.error(f"unknown experiment {args.name!r}; choose one of {', '.join(EXPERIMENTS)}")
    command = "python -m a2catvn_jax.experiments " + " ".join(argv if argv is not None else sys.argv[1:])
    with cli.errors(parser, code=1), cli.errors(parser, code=2, kinds=(ConfigError, ExperimentError, ValueError)):
        run_experiment(EXPERIMENTS[args.name], scale=args.scale, seeds=args.seeds, episodes=args.episodes,
                       root=args.root, docs=args.docs, overrides=cli.overrides_of(args),
                       command=command.strip(), threshold=args.threshold)


if __name__ == "__main__":
    main()
