"""The training loop: build the environment and the update, restore or start a run, update, log, checkpoint.

`train(cfg, workdir)` runs `train.total_frames` frames (or `max_updates` updates) of
the jitted update, `train.updates_per_call` of them per call (a loop on the device;
default: `train.log_every`), with the environments split over the local devices;
it writes metrics every `train.log_every` updates and orbax checkpoints every
`train.checkpoint_every` updates and on exit (Ctrl-C included), all at call
boundaries. `resume=True` continues the run in `workdir` from its latest checkpoint:
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

import jax
import numpy as np
from jax.sharding import Mesh
from tqdm import tqdm

from a2catvn_jax.agent.networks import make_networks
from a2catvn_jax.agent.update import (NONFINITE, UPDATES, frames_per_update, make_grad_norms, make_update, repeated,
                                      sharding_of, total_updates)
from a2catvn_jax.env import NavEnv
from a2catvn_jax.errors import UserError
from a2catvn_jax.run.checkpoint import DATA_FORMAT, Checkpointer, CheckpointError
from a2catvn_jax.run.logger import Interval, MetricsWriter
from a2catvn_jax.run.pretraining import load_matching


class TrainingError(UserError, RuntimeError):
    """The run cannot go on (a non-finite loss)."""


class _StopFlag:
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


@functools.lru_cache(maxsize=1)
def _build(cfg):
    """(environment, networks, its jitted init and update, grad-norm diagnostic or None) of
    `cfg`, whose seed (only the run's first key) is zeroed. The last configuration's are
    kept: another run of it in this process (a notebook cell run again, the next seed of
    an experiment) traces and compiles nothing again."""
    env = NavEnv(cfg.env)
    networks = make_networks(cfg, env.num_actions)
    grad_norms = make_grad_norms(env, networks, cfg) if cfg.train.grad_norm_every else None
    return env, networks, make_update(env, networks, cfg), grad_norms


def devices_for(cfg, devices=None) -> list:
    """The local devices a run of `cfg` uses: all of them, or the first `devices`; the
    environments must split evenly over them."""
    local = jax.local_devices()
    n = len(local) if devices is None else int(devices)
    if not 1 <= n <= len(local):
        raise TrainingError(f"--devices {n}: this machine has {len(local)} {local[0].platform} device(s)")
    if cfg.env.num_envs % n:
        raise TrainingError(f"env.num_envs={cfg.env.num_envs} environments cannot be split evenly over {n} devices: "
                            f"make it a multiple of {n} or pass --devices")
    return local[:n]


def updates_per_call(cfg) -> int:
    """Updates one call of the compiled loop runs at most (`train.updates_per_call`, 0: `train.log_every`)."""
    return cfg.train.updates_per_call or cfg.train.log_every


def next_stop(update: int, end: int, cfg) -> int:
    """The update count the call starting at `update` runs to: the next multiple of the
    updates per call, of `train.log_every` or of `train.checkpoint_every`, or `end`,
    whichever comes first (calls align to counts, so a resumed run's calls are the same)."""
    tc = cfg.train
    return min([end] + [(update // k + 1) * k for k in (updates_per_call(cfg), tc.log_every, tc.checkpoint_every)])


def train(cfg, workdir, *, resume: bool = False, max_updates=None, progress: bool = True, log=None, init_from=None,
          devices=None):
    """Train `cfg` in `workdir`; returns (environment, final train state, last log row).

    `max_updates` bounds the updates of this call (default: up to train.total_frames);
    `log` receives the text lines (default: print). `init_from` is a pre-training work
    directory (`python -m a2catvn_jax.pretrain`) whose matching parameters a new run
    starts from. `devices`: how many local devices to split the environments over (default: all).
    """
    log = log or functools.partial(print, flush=True)
    workdir = Path(workdir)
    used = devices_for(cfg, devices)
    ckpt = Checkpointer(workdir, keep=cfg.train.keep_checkpoints)
    if ckpt.steps() and not resume:
        raise CheckpointError(
            f"{workdir} already holds checkpoints (updates {ckpt.steps()}); pass --resume to continue that run "
            f"or choose another --workdir"
        )
    t_build = time.perf_counter()
    env, networks, (init, update_fn), grad_norms = _build(dataclasses.replace(cfg, seed=0))
    per_update = frames_per_update(cfg)
    where = f" on {len(used)} {used[0].platform} devices" if len(used) > 1 else ""
    log(f"built {env.num_scenes} scene(s), {env.num_actions} actions, "
        f"{env.num_envs} environments{where} in {time.perf_counter() - t_build:.1f} s, rendered by {env.world.backend}")
    if env.world.backend_note:
        log(env.world.backend_note)
    key = jax.random.PRNGKey(cfg.seed)
    if resume:
        template = jax.eval_shape(init, key)
        state, meta = ckpt.restore(template, cfg)
        if meta.get("format", 1) < DATA_FORMAT:  # written before the state held its mjx.Data
            state = state.replace(env_state=env.with_data(state.env_state))
        log(f"resumed from update {meta['update']} ({meta['frames']:,} frames)")
    else:
        state = init(key)
        if init_from is not None:
            params, loaded, kept = load_matching(state.params, init_from)
            state = init(key, params)  # the same state with the loaded parameters and their optimiser state
            log(f"initialised from {init_from}: {len(loaded)} arrays of {_modules(loaded)}; "
                f"{len(kept)} arrays keep their initial values ({_modules(kept)})")
    layout = None
    if len(used) > 1:  # the environment axis split over the devices, the rest replicated
        layout = sharding_of(state, Mesh(np.array(used), ("batch",)))
        state = jax.device_put(state, layout)
    if not resume:
        ckpt.save(state, cfg, 0)
    # One compile serves the whole run: the loop of updates is compiled ahead of time for
    # this state, and a state of other shapes or dtypes would be an error, not a recompile.
    t_compile = time.perf_counter()
    run_updates = repeated(update_fn, layout).lower(state, np.int32(1)).compile()
    log(f"compiled the update in {time.perf_counter() - t_compile:.1f} s")
    start = int(state.update)
    last = total_updates(cfg)
    end = last if max_updates is None else min(last, start + max_updates)
    writer = MetricsWriter(workdir)
    interval = Interval()
    stop = _StopFlag()
    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    bar = None
    if progress:
        bar = tqdm(total=end, initial=start, unit="upd", dynamic_ncols=True, file=sys.stderr)
    row = {}
    clean_exit = False
    t_log, frames_log = time.perf_counter(), start * per_update
    try:
        update = start
        while update < end and not stop.stop:
            n = next_stop(update, end, cfg) - update
            new_state, sums = run_updates(state, np.int32(n))
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
                    row.update({k: float(v) for k, v in jax.device_get(grad_norms(state)).items()})
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
        clean_exit = True
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if bar is not None:
            bar.close()
        writer.close()
        # After a failure the state handed to the loop is gone (its buffers are donated):
        # the last checkpoint stays the run's last good state.
        if clean_exit:
            saved = ckpt.save(state, cfg, int(state.update) * per_update)
            log(f"checkpoint at update {saved} in {ckpt.directory}")
        ckpt.close()
    return env, state, row


def _modules(paths) -> str:
    """The layer names of parameter paths like "['params']['conv1']['kernel']"."""
    names = [p.split("']['")[1] if "']['" in p else p for p in paths]
    return ", ".join(dict.fromkeys(names)) or "none"


def _fmt(x, spec=".2f"):
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)
