"""Train an A2CAT-VN agent.

    python -m a2catvn_jax.train [--config configs/NAME.yaml] [--workdir DIR] [--set KEY=VALUE ...]
        [--resume] [--updates N] [--init-from PRETRAIN_DIR]

With no arguments it trains the quickstart configuration (`configs/quickstart.yaml`)
in `runs/quickstart`. The work directory receives `config.yaml`, orbax checkpoints
(`checkpoints/`, every `train.checkpoint_every` updates and on exit, Ctrl-C
included), `metrics.jsonl`, `metrics.csv` and TensorBoard logs (`tb/`).

`--resume` continues the run in the work directory from its latest checkpoint, with
the configuration saved there: training N updates, stopping and resuming for N more
gives the same parameters as 2N updates in one go. A non-finite loss stops the run
with an error and leaves the last good checkpoint in place.
"""

from __future__ import annotations

import argparse
import functools
import math
import signal
import sys
import time
from pathlib import Path

from a2catvn_jax.config import ConfigError, add_config_args, config_from_args, load_config

DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "quickstart.yaml"
DEFAULT_WORKDIR = "runs/quickstart"


class TrainingError(RuntimeError):
    """The run cannot go on (a non-finite loss)."""


class _StopFlag:
    """First Ctrl-C asks the loop to stop after the current update; the second interrupts."""

    def __init__(self):
        self.stop = False

    def __call__(self, signum, frame):
        if self.stop:
            raise KeyboardInterrupt
        self.stop = True
        print("\nstopping after this update (Ctrl-C again to abort without a checkpoint)", file=sys.stderr)


def train(cfg, workdir, *, resume: bool = False, max_updates=None, progress: bool = True, log=None, init_from=None):
    """Train `cfg` in `workdir`; returns (learner, final train state, last log row).

    `max_updates` bounds the updates of this call (default: up to train.total_frames);
    `log` receives the text lines (default: print). `init_from` is a pre-training work
    directory (`python -m a2catvn_jax.pretrain`) whose matching parameters a new run starts from.
    """
    log = log or functools.partial(print, flush=True)
    import jax

    from a2catvn_jax.checkpoint import Checkpointer, CheckpointError
    from a2catvn_jax.learner import Learner
    from a2catvn_jax.logger import Interval, MetricsWriter

    workdir = Path(workdir)
    ckpt = Checkpointer(workdir, keep=cfg.train.keep_checkpoints)
    if ckpt.steps() and not resume:
        raise CheckpointError(
            f"{workdir} already holds checkpoints (updates {ckpt.steps()}); pass --resume to continue that run "
            f"or choose another --workdir"
        )
    t_build = time.perf_counter()
    learner = Learner(cfg)
    log(f"built {learner.env.num_scenes} scene(s), {learner.env.num_actions} actions, "
        f"{learner.B} environments in {time.perf_counter() - t_build:.1f} s")
    key = jax.random.PRNGKey(cfg.seed)
    if resume:
        template = jax.eval_shape(learner.init, key)
        state, meta = ckpt.restore(template, cfg)
        log(f"resumed from update {meta['update']} ({meta['frames']:,} frames)")
    else:
        state = learner.init(key)
        if init_from is not None:
            from a2catvn_jax.pretrain import load_matching

            params, loaded, kept = load_matching(state.params, init_from)
            state = state.replace(params=params, opt_state=learner.optimizer.init(params))
            log(f"initialised from {init_from}: {len(loaded)} arrays of {_modules(loaded)}; "
                f"{len(kept)} arrays keep their initial values ({_modules(kept)})")
        ckpt.save(state, cfg, 0)
    start = int(state.update)
    end = learner.total_updates if max_updates is None else min(learner.total_updates, start + max_updates)
    writer = MetricsWriter(workdir)
    interval = Interval()
    stop = _StopFlag()
    previous = signal.signal(signal.SIGINT, stop)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=end, initial=start, unit="upd", dynamic_ncols=True, file=sys.stderr)
    row = {}
    clean_exit = False
    t_log, frames_log = time.perf_counter(), start * learner.frames_per_update
    try:
        update = start
        while update < end and not stop.stop:
            new_state, metrics = learner.update(state)
            metrics = jax.device_get(metrics)
            if not all(math.isfinite(float(v)) for v in metrics.values()):
                bad = sorted(k for k, v in metrics.items() if not math.isfinite(float(v)))
                raise TrainingError(
                    f"non-finite value at update {update + 1} in {', '.join(bad)}; stopping. The last good "
                    f"checkpoint (update {ckpt.latest()}) in {ckpt.directory} is kept."
                )
            state = new_state
            update += 1
            interval.add(metrics)
            if bar is not None:
                bar.update(1)
            if update % cfg.train.log_every == 0 or update == end:
                now, frames = time.perf_counter(), update * learner.frames_per_update
                row = {"update": update, "frames": frames, "fps": (frames - frames_log) / max(now - t_log, 1e-9),
                       **interval.row()}
                writer.write(row)
                interval.reset()
                t_log, frames_log = now, frames
                if bar is not None:
                    bar.set_postfix(fps=f"{row['fps']:.0f}", success=_fmt(row["success_rate"]),
                                    ep_len=_fmt(row["episode_length"], ".0f"), loss=f"{row['loss/total']:.3f}")
                else:
                    log(f"update {update} frames {frames:,} fps {row['fps']:.0f} success {_fmt(row['success_rate'])} "
                        f"length {_fmt(row['episode_length'], '.0f')} spl {_fmt(row['spl'])}")
            if update % cfg.train.checkpoint_every == 0:
                ckpt.save(state, cfg, update * learner.frames_per_update)
        clean_exit = True
    finally:
        signal.signal(signal.SIGINT, previous)
        if bar is not None:
            bar.close()
        writer.close()
        # After a failure the state handed to `update` is gone (its buffers are donated):
        # the last checkpoint stays the run's last good state.
        if clean_exit:
            saved = ckpt.save(state, cfg, int(state.update) * learner.frames_per_update)
            log(f"checkpoint at update {saved} in {ckpt.directory}")
        ckpt.close()
    return learner, state, row


def _modules(paths) -> str:
    """The layer names of parameter paths like "['params']['conv1']['kernel']"."""
    names = [p.split("']['")[1] if "']['" in p else p for p in paths]
    return ", ".join(dict.fromkeys(names)) or "none"


def _fmt(x, spec=".2f"):
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m a2catvn_jax.train", description=__doc__.split("\n\n")[0])
    add_config_args(parser)
    parser.add_argument("--workdir", default=None, help=f"run directory (default {DEFAULT_WORKDIR})")
    parser.add_argument("--resume", action="store_true", help="continue the run in --workdir from its latest checkpoint")
    parser.add_argument("--updates", type=int, default=None, help="stop after this many updates (default: to train.total_frames)")
    parser.add_argument("--no-progress", action="store_true", help="log lines instead of a progress bar")
    parser.add_argument("--init-from", metavar="DIR", default=None,
                        help="start a new run from the matching parameters of a pre-training work directory")
    args = parser.parse_args(argv)
    workdir = Path(args.workdir or DEFAULT_WORKDIR)
    if args.updates is not None and args.updates < 1:
        parser.error(f"--updates must be >= 1, got {args.updates}")
    if args.init_from and args.resume:
        parser.error("--init-from starts a new run; it cannot be combined with --resume")

    from a2catvn_jax.checkpoint import CHECKPOINT_DIR, CheckpointError, read_run_config
    from a2catvn_jax.pretrain import PretrainError

    try:
        if args.resume:
            if not (workdir / CHECKPOINT_DIR).is_dir():
                raise CheckpointError(f"--resume: {workdir} holds no checkpoints")
            cfg = read_run_config(workdir)
            if args.config is not None or args.overrides:
                from a2catvn_jax.checkpoint import config_differences

                given = config_from_args(args)
                diff = config_differences(cfg, given)
                if diff:
                    raise CheckpointError(
                        f"--resume: the given configuration differs from the run's ({workdir / 'config.yaml'}):\n  "
                        + "\n  ".join(diff)
                    )
                cfg = given
        elif args.config is None:
            cfg = load_config(DEFAULT_CONFIG, [o for group in args.overrides for o in group])
        else:
            cfg = config_from_args(args)
    except ConfigError as e:
        parser.error(str(e))
    except CheckpointError as e:
        parser.exit(2, f"error: {e}\n")

    try:
        train(cfg, workdir, resume=args.resume, max_updates=args.updates, progress=not args.no_progress,
              init_from=args.init_from)
    except (CheckpointError, TrainingError, PretrainError) as e:
        parser.exit(1, f"error: {e}\n")


if __name__ == "__main__":
    main()
