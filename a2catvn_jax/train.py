"""Train an A2CAT-VN agent.

    python -m a2catvn_jax.train [--config configs/NAME.yaml [MORE.yaml ...]] [--workdir DIR] [--set KEY=VALUE ...]
        [--resume [--step N]] [--updates N] [--init-from PRETRAIN_DIR] [--devices N]
        [--coordinator-address HOST:PORT --num-processes N --process-id I]

With no arguments it trains the quickstart configuration (`configs/quickstart.yaml`)
in `runs/quickstart`. The work directory receives `config.yaml`, orbax checkpoints
(`checkpoints/`, every `train.checkpoint_every` updates and on exit, Ctrl-C or SIGTERM
included), `metrics.jsonl`, `metrics.csv` and TensorBoard logs (`tb/`).

`--resume` continues the run in the work directory from its latest checkpoint, with
the configuration saved there: training N updates, stopping and resuming for N more
gives the same parameters as 2N updates in one go. A non-finite loss stops the run
with an error and leaves the last good checkpoint in place. The environments are split
over every local device (`--devices N`: the first N); the results are those of one
device at the same batch, to float rounding. Several processes (one per machine) train
one run when started with the same command and `--coordinator-address`,
`--num-processes` and each its own `--process-id` (or under SLURM / Open MPI, which
give them): each steps its share of the environments, process 0 logs, all of them
write each checkpoint together.

A work directory has one writer at a time: a second `train` (or `pretrain`) there
stops with a line naming the process that holds it. When the latest checkpoint cannot
be read, `--resume` says which can; `--resume --step N` goes on from checkpoint N
(and removes the ones after it). A failed write (a full disk included) stops the run
with one line naming the last complete checkpoint; a batch too large for the memory is
refused before anything is allocated.
"""

from __future__ import annotations

import argparse
import signal
from pathlib import Path

from a2catvn_jax import cli
from a2catvn_jax.config import CONFIGS
from a2catvn_jax.errors import UserError
from a2catvn_jax.run import distributed
from a2catvn_jax.run.checkpoint import CHECKPOINT_DIR, CheckpointError, config_differences, read_run_config
from a2catvn_jax.run.training import StopFlag, train

DEFAULT_CONFIG = CONFIGS / "quickstart.yaml"
DEFAULT_WORKDIR = "runs/quickstart"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m a2catvn_jax.train", description=__doc__.split("\n\n")[0])
    cli.add_config_args(parser)
    parser.add_argument("--workdir", default=None, help=f"run directory (default {DEFAULT_WORKDIR})")
    parser.add_argument("--resume", action="store_true", help="continue the run in --workdir from its latest checkpoint")
    parser.add_argument("--step", type=int, default=None, metavar="N",
                        help="with --resume: continue from the checkpoint of update N (the ones after it are removed)")
    parser.add_argument("--updates", type=int, default=None, help="stop after this many updates (default: to train.total_frames)")
    parser.add_argument("--no-progress", action="store_true", help="log lines instead of a progress bar")
    parser.add_argument("--init-from", metavar="DIR", default=None,
                        help="start a new run from the matching parameters of a pre-training work directory")
    parser.add_argument("--devices", type=int, default=None, metavar="N",
                        help="split the environments over the first N local devices (default: all of them)")
    several = parser.add_argument_group(
        "several processes (one per machine or accelerator; jax.distributed reads these from SLURM or Open MPI "
        "when they are left out)")
    several.add_argument("--coordinator-address", metavar="HOST:PORT", default=None,
                         help="where process 0 listens for the others")
    several.add_argument("--num-processes", type=int, default=None, metavar="N", help="processes in the run")
    several.add_argument("--process-id", type=int, default=None, metavar="I", help="this process's rank, 0..N-1")
    args = parser.parse_args(argv)
    workdir = Path(args.workdir or DEFAULT_WORKDIR)
    if args.updates is not None and args.updates < 1:
        parser.error(f"--updates must be >= 1, got {args.updates}")
    if args.devices is not None and args.devices < 1:
        parser.error(f"--devices must be >= 1, got {args.devices}")
    if args.init_from and args.resume:
        parser.error("--init-from starts a new run; it cannot be combined with --resume")
    if args.step is not None and not args.resume:
        parser.error("--step N chooses the checkpoint to resume from: it needs --resume")

    # SIGTERM (a scheduler's) asks for a stop with a checkpoint from now on: before the first
    # update the run stops there, and after the run it is ignored while the process exits
    # (with several processes, a signal that reaches one after all stopped must not kill it).
    stop = StopFlag()
    before = signal.signal(signal.SIGTERM, stop)
    try:
        _run(parser, args, workdir, stop)
    finally:
        signal.signal(signal.SIGTERM, before)  # then `cli.run_stoppable` ignores it while the process exits


def _run(parser, args, workdir: Path, stop: StopFlag) -> None:
    with cli.errors(parser, code=2):
        distributed.initialize(args.coordinator_address, args.num_processes, args.process_id)
        if args.resume:
            if not (workdir / CHECKPOINT_DIR).is_dir():
                raise CheckpointError(f"--resume: {workdir} holds no checkpoints")
            cfg = read_run_config(workdir)
            if args.config is not None or args.overrides:
                given = cli.config_from_args(args)
                diff = config_differences(cfg, given)
                if diff:
                    raise CheckpointError(
                        f"--resume: the given configuration differs from the run's ({workdir / 'config.yaml'}):\n  "
                        + "\n  ".join(diff)
                    )
                cfg = given
        else:
            cfg = cli.config_from_args(args, default=DEFAULT_CONFIG)

    with cli.errors(parser, code=1, kinds=(UserError, OSError)):  # OSError: a file the run could not write
        try:
            train(cfg, workdir, resume=args.resume, max_updates=args.updates, progress=not args.no_progress,
                  init_from=args.init_from, devices=args.devices, step=args.step, stop=stop)
        except KeyboardInterrupt:
            parser.exit(130, f"aborted without a checkpoint; `--workdir {workdir} --resume` goes on from the last one\n")


if __name__ == "__main__":
    cli.run_stoppable(main)
