"""The training loop: build the environment and the update, restore or start a run, update, log, checkpoint.

`train(cfg, workdir)` runs `train.total_frames` frames (or `max_updates` updates) of
the jitted update, `train.updates_per_call` of them per call (a loop on the device;
default: `train.log_every` on an accelerator, 1 on the CPU, where a loop around the
update halves its speed), with the environments split over the local devices;
it writes metrics every `train.log_every` updates, orbax checkpoints every
`train.checkpoint_every` updates and on exit (Ctrl-C included), and evaluations every
`train.eval.every` updates (run/training_eval.py), all at call boundaries. `resume=True` continues the run in `workdir` from its latest checkpoint:
N updates, stop, resume, N more gives the parameters of 2N updates in one go. A
non-finite loss stops the run with a `TrainingError` and leaves the last good checkpoint.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import signal
import sys
import time
from pathlib import Path
from typing import Optional

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm import tqdm

from a2catvn_jax.agent.networks import make_networks
from a2catvn_jax.agent.update import (NONFINITE, UPDATES, frames_per_update, make_grad_norms, make_renew, make_update,
                                      repeated, sharding_of, total_updates)
from a2catvn_jax.env import make_env
from a2catvn_jax.env.world import new_houses
from a2catvn_jax.errors import UserError
from a2catvn_jax.memo import Memo
from a2catvn_jax.run import distributed
from a2catvn_jax.run.checkpoint import DATA_FORMAT, Checkpointer, CheckpointError
from a2catvn_jax.run.logger import Interval, MetricsWriter, truncate_metrics
from a2catvn_jax.run.memory import checked_compile
from a2catvn_jax.run.pretraining import load_matching
from a2catvn_jax.run.training_eval import TrainingEval
from a2catvn_jax.run.workdir import locked


class TrainingError(UserError, RuntimeError):
    """The run cannot go on (a non-finite loss)."""


class StopFlag:
    """Ctrl-C or SIGTERM (as `timeout` and job schedulers send) asks the loop to stop after
    the current update and checkpoint. A second Ctrl-C interrupts; a second SIGTERM is the
    same request again (`timeout` sends one to the command and one to its process group)."""

    def __init__(self):
        self.stop = False

    def __call__(self, signum, frame):
        if self.stop:
            if signum == signal.SIGINT:
                raise KeyboardInterrupt
            return
        self.stop = True
        again = " (Ctrl-C again to abort without a checkpoint)" if signum == signal.SIGINT else ""
        print(f"\nstopping after the updates in progress{again}", file=sys.stderr)


# The compiled update loops of the last two (configuration, devices, updates per call):
# another run of one in this process (the next seed of an experiment, a notebook cell run
# again, a resume) compiles nothing again.
COMPILED = Memo("training's compiled update loops", keep=2)


@functools.lru_cache(maxsize=1)
def _build(cfg):
    """(environment, networks, its jitted init and update, grad-norm diagnostic or None) of
    `cfg`, whose seed (only the run's first key) is zeroed. The last configuration's are
    kept: another run of it in this process (a notebook cell run again, the next seed of
    an experiment) traces and compiles nothing again."""
    env = make_env(cfg.env)
    networks = make_networks(cfg, env.num_actions)
    grad_norms = make_grad_norms(env, networks, cfg) if cfg.train.grad_norm_every else None
    renew = make_renew(env, networks, cfg) if cfg.train.new_houses_every else None
    return env, networks, make_update(env, networks, cfg), grad_norms, renew


def updates_per_call(cfg, platform: Optional[str] = None) -> int:
    """Updates one call runs at most: `train.updates_per_call`, or by default 1 on the CPU
    (a device loop around the update runs at half the speed there: docs/benchmarks.md,
    "Updates per call") and `train.log_every` on an accelerator."""
    platform = platform or jax.default_backend()
    return cfg.train.updates_per_call or (1 if platform == "cpu" else cfg.train.log_every)


def next_stop(update: int, end: int, cfg, per_call: int) -> int:
    """The update count the call starting at `update` runs to: the next multiple of
    `per_call`, of `train.log_every`, `train.checkpoint_every` or `train.eval.every`, or `end`, whichever
    comes first (calls align to counts, so a resumed run's calls are the same)."""
    tc = cfg.train
    periods = ((per_call, tc.log_every, tc.checkpoint_every) + ((tc.eval.every,) if tc.eval.every else ())
               + ((tc.new_houses_every,) if tc.new_houses_every else ()))
    return min([end] + [(update // k + 1) * k for k in periods])


@locked("train")  # one writer per work directory (run/workdir.py)
def train(cfg, workdir, *, resume: bool = False, max_updates=None, progress: bool = True, log=None, init_from=None,
          devices=None, step=None, stop: Optional["StopFlag"] = None):
    """Train `cfg` in `workdir`; returns (environment, final train state, last log row).

    `max_updates` bounds the updates of this call (default: up to train.total_frames);
    `log` receives the text lines (default: print). `init_from` is a pre-training work
    directory (`python -m a2catvn_jax.pretrain`) whose matching parameters a new run
    starts from. `devices`: how many local devices to split the environments over (default: all).
    `step`: with `resume`, the checkpoint to go on from (default: the latest); the ones after it are removed.
    `stop`: the `StopFlag` a caller installed for SIGTERM before the run was built (the
    command line), so that a signal before the first update stops the run there too.
    """
    main = distributed.is_main()  # with several processes, process 0 logs and tidies the work directory
    log = (log or functools.partial(print, flush=True)) if main else (lambda *_: None)
    progress = progress and main
    workdir = Path(workdir)
    used = distributed.devices_for(cfg.env.num_envs, devices)
    if init_from is not None and jax.process_count() > 1:
        raise TrainingError("--init-from is not supported in a run of several processes: start it in one process, "
                            "stop it after its first checkpoint, and --resume it with all of them")
    if cfg.train.eval.every and jax.process_count() > 1:
        raise TrainingError("train.eval.every: evaluation during training runs in a single process; evaluate the "
                            "run's checkpoints with python -m a2catvn_jax.evaluate")
    ckpt = Checkpointer(workdir, keep=cfg.train.keep_checkpoints)
    if main:
        ckpt.remove_partial(log)  # half-written checkpoints of a run that stopped while writing one
    if step is not None and not resume:
        raise CheckpointError(f"--step {step} chooses the checkpoint to resume from: it needs --resume")
    if ckpt.steps() and not resume:
        raise CheckpointError(
            f"{workdir} already holds checkpoints (updates {ckpt.steps()}); pass --resume to continue that run "
            f"or choose another --workdir"
        )
    t_build = time.perf_counter()
    if cfg.train.new_houses_every and jax.process_count() > 1:
        raise TrainingError("train.new_houses_every: new houses are built in a single process; train with one process")
    env, networks, (init, update_fn), grad_norms, renew_fn = _build(dataclasses.replace(cfg, seed=0))
    if renew_fn is not None:
        check_renewable(env)
    per_update = frames_per_update(cfg)
    where = f" on {len(used)} {used[0].platform} devices" if len(used) > 1 else ""
    if jax.process_count() > 1:
        where += f" of {jax.process_count()} processes"
    log(f"built {env.num_scenes} scene(s), {env.num_actions} actions, "
        f"{env.num_envs} environments{where} in {time.perf_counter() - t_build:.1f} s, rendered by {env.renderer}")
    for line in env.render_notes(env.num_envs // len(used), used[0].platform):
        log(line)
    key = jax.random.PRNGKey(cfg.seed)
    template = jax.eval_shape(init, key)
    layout = replicated = None
    if len(used) > 1:  # the environment axis split over the devices, the rest replicated
        mesh = Mesh(np.array(used), ("batch",))
        layout, replicated = sharding_of(template, mesh), NamedSharding(mesh, PartitionSpec())
    # With train.new_houses_every the houses are an argument of the update (data): each new
    # set is passed to the same compiled update.
    houses = None if renew_fn is None else jax.eval_shape(lambda: env.world.arrays)
    # One compile serves the whole run: the loop of updates is compiled ahead of time for
    # the abstract state, and a state of other shapes or dtypes would be an error, not a
    # recompile. Its memory and the state's are checked before either is allocated (run/memory.py).
    per_call = updates_per_call(cfg, used[0].platform)
    t_compile = time.perf_counter()
    compiled_key = (dataclasses.replace(cfg, seed=0), tuple((d.process_index, d.id) for d in used), per_call)
    reused = compiled_key in COMPILED
    run_updates, memory = checked_compile(
        cfg, env, lambda abstract: COMPILED.get(compiled_key, lambda: repeated(update_fn, layout, loop=per_call > 1)
                                                .lower(abstract, np.int32(1), houses).compile()),
        template, used)
    log((f"compiled the update in {time.perf_counter() - t_compile:.1f} s; " if not reused
         else "the update compiled by an earlier run of this configuration in this process is reused; ")
        + (f"{per_call} updates per call" if per_call > 1 else "one update per call")
        + ("" if cfg.train.updates_per_call else f" (the default on {used[0].platform})"))
    log(memory)
    if resume:
        # With several processes each restores its own shards of the one checkpoint.
        state, meta = ckpt.restore(template if jax.process_count() == 1 else _placed(template, layout), cfg, step)
        if meta.get("format", 1) < DATA_FORMAT:  # written before the state held its mjx.Data
            state = state.replace(env_state=env.with_data(state.env_state))
        log(f"resumed from update {meta['update']} ({meta['frames']:,} frames)")
        if main:
            ckpt.discard_after(int(meta["update"]), log)
    else:
        state = init(key)
        if init_from is not None:
            params, loaded, kept = load_matching(state.params, init_from)
            state = init(key, params)  # the same state with the loaded parameters and their optimiser state
            log(f"initialised from {init_from}: {len(loaded)} arrays of {_modules(loaded)}; "
                f"{len(kept)} arrays keep their initial values ({_modules(kept)})")
    if layout is not None:
        state = place(state, layout)
    if not resume:
        ckpt.save(state, cfg, 0)
    start = int(state.update)
    every = cfg.train.new_houses_every
    last = total_updates(cfg)
    end = last if max_updates is None else min(last, start + max_updates)
    renew = world = ahead = None
    if every:
        renew = (jax.jit(renew_fn, donate_argnums=0) if layout is None else
                 jax.jit(renew_fn, donate_argnums=0, in_shardings=(layout, replicated), out_shardings=layout))
        log(f"new houses every {every} updates ({every * per_update:,} frames): {env.num_scenes} newly generated "
            f"scenes each time")
        if start < end and (start % every or start == 0):  # the houses the state is in (at a multiple of `every` the loop moves it on)
            world = _new_houses(env, start // every, replicated, log)
        if start == 0 and end > every:  # built now, so that houses that cannot be built stop the run before it trains
            ahead = (1, _new_houses(env, 1, replicated, log))
    writer = None
    if main:
        dropped = truncate_metrics(workdir, start)  # rows past the checkpoint: the run writes them again
        if dropped:
            log(f"removed {dropped} row(s) after update {start} from {workdir / 'metrics.jsonl'}: the run logs them again")
        writer = MetricsWriter(workdir, note=ckpt.last_complete, purge_step=start * per_update + 1 if start else None)
    interval = Interval()
    stop = stop or StopFlag()
    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    bar = None
    if progress:
        bar = tqdm(total=end, initial=start, unit="upd", dynamic_ncols=True, file=sys.stderr)
    row = {}
    clean_exit = False
    try:
        # Its lines go above the progress bar, not through it.
        evaluator = (TrainingEval(cfg, networks, workdir, start, len(used), bar.write if bar is not None else log)
                     if cfg.train.eval.every else None)
        t_log, frames_log = time.perf_counter(), start * per_update
        update = start
        # Every process asks the others at each call: a signal that reaches them a moment
        # apart stops all of them after the same update.
        while update < end and not distributed.any_process(stop.stop):
            if every and update % every == 0 and update > 0:
                t_houses = time.perf_counter()
                generation = update // every
                world = ahead[1] if ahead and ahead[0] == generation else _new_houses(env, generation, replicated, log)
                ahead = None
                state = renew(state, world)
                t_log += time.perf_counter() - t_houses  # the logged frames/s counts training time only
            n = next_stop(update, end, cfg, per_call) - update
            new_state, sums = run_updates(state, np.int32(n), world)
            sums = jax.device_get(sums)
            bad_at = int(sums.pop(NONFINITE))
            count = int(sums.pop(UPDATES))
            if bad_at:
                bad = sorted(k for k, v in sums.items() if not math.isfinite(float(v)))
                raise TrainingError(
                    f"non-finite value at update {update + bad_at} in {', '.join(bad) or 'the metrics'}; stopping. "
                    f"The last good checkpoint (update {ckpt.latest()}) in {ckpt.directory} is kept."
                )
            state = new_state
            update += count
            interval.add(sums, updates=count)
            if bar is not None:
                bar.update(count)
            if update % cfg.train.log_every == 0 or update == end:
                now, frames = time.perf_counter(), update * per_update
                row = {"update": update, "frames": frames, "fps": (frames - frames_log) / max(now - t_log, 1e-9),
                       **interval.row()}
                if grad_norms is not None and update % cfg.train.grad_norm_every == 0:
                    row.update({k: float(v) for k, v in jax.device_get(grad_norms(state, world)).items()})
                if writer is not None:
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
                ckpt.save(state, cfg, update * per_update)
            if evaluator is not None and evaluator.due(update):
                t_eval = time.perf_counter()
                evaluator(state.params, update, update * per_update)
                t_log += time.perf_counter() - t_eval  # the logged frames/s counts training time only
        clean_exit = True
    finally:
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.close()
        # After a failure the state handed to the loop is gone (its buffers are donated):
        # the last checkpoint stays the run's last good state. The stop handler stays in
        # place while the last checkpoint is written (all processes write it together).
        try:
            if clean_exit:
                saved = ckpt.save(state, cfg, int(state.update) * per_update)
                log(f"checkpoint at update {saved} in {ckpt.directory}")
            ckpt.close()
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
    return env, state, row


def check_renewable(env) -> None:
    """Refuse, in one line, a world whose houses `train.new_houses_every` cannot renew: new
    houses are rendered by the ray caster (`env.render.backend=auto` may resolve to mjx
    on an accelerator, which the configuration's own checks cannot see)."""
    if env.renderer != "raycast":
        raise TrainingError(f"train.new_houses_every: new houses are rendered by the ray caster; this run renders "
                            f"with {env.renderer!r} (set env.render.backend=raycast)")


def _new_houses(env, generation: int, replicated, log):
    """The world arrays of the training houses' replacement `generation` (0: the
    environment's own houses), replicated over the devices when `replicated` is a sharding."""
    if generation == 0:
        world = env.world.arrays
    else:
        t0 = time.perf_counter()
        world, drawn = new_houses(env.world, generation)
        log(f"new houses {generation}: {env.num_scenes} scenes (the first that fit of {drawn} drawn) built in "
            f"{time.perf_counter() - t0:.1f} s")
    return world if replicated is None else jax.device_put(world, replicated)


def place(tree, layout):
    """`tree` laid out as `layout` (a tree of shardings): arrays already placed so stay,
    the others (the same value in every process) are put there from host memory."""
    return jax.tree_util.tree_map(
        lambda x, s: x if getattr(x, "sharding", None) == s else jax.device_put(np.asarray(x), s), tree, layout)


def _placed(template, layout):
    """The abstract `template` with each leaf's sharding: what a checkpoint restores into."""
    return jax.tree_util.tree_map(lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s), template, layout)


def _modules(paths) -> str:
    """The layer names of parameter paths like "['params']['conv1']['kernel']"."""
    names = [p.split("']['")[1] if "']['" in p else p for p in paths]
    return ", ".join(dict.fromkeys(names)) or "none"


def _fmt(x, spec=".2f"):
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)
