"""Orbax checkpoints of a training run.

A work directory holds `config.yaml` (the run's full configuration) and
`checkpoints/<update>/` written by an orbax `CheckpointManager`: the whole
`TrainState` (parameters, optimiser state, environment and agent state, replay
buffer, PRNG key, update count) and a small JSON record (update, frames, config).
Restoring it and calling `update` continues the run exactly where it stopped.

Every problem is a `CheckpointError` that says what is wrong: no checkpoint in the
directory, a step that does not exist, a checkpoint that cannot be read (with the
checkpoints that can: `--step N` goes on from one of them), one written under a
different configuration (the differing keys are listed), or a write that failed (a full
disk included; the last complete checkpoint is named).

Orbax writes a checkpoint to `<update>.orbax-checkpoint-tmp-*` and renames it when it is
complete, so readers only ever see complete ones. The run that writes the directory
(the holder of its lock, `run.workdir`) removes what a write that did not finish left
behind (`remove_partial`), and the checkpoints after the one it resumes from
(`discard_after`).
"""

from __future__ import annotations

import copy
import errno
import logging
import os
import shutil
import sys
import warnings
from pathlib import Path
from typing import Optional

import jax
import numpy as np
import orbax.checkpoint as ocp
import yaml

from a2catvn_jax.config import Config, ConfigError, config_keys, from_dict, load_config, save_config, to_dict
from a2catvn_jax.configio import flat
from a2catvn_jax.errors import UserError

CONFIG_FILE = "config.yaml"
CHECKPOINT_DIR = "checkpoints"
PARTIAL = ".orbax-checkpoint-tmp"  # the suffix (then -<time>) of a checkpoint orbax is still writing
# The keys of evaluation during training: what a run measures while it trains, not what it trains.
EVAL_KEYS = tuple(k for k in config_keys() if k.startswith("train.eval."))
# Keys that may differ between the run that wrote a checkpoint and the one resuming it
# (how often it logs, saves and evaluates; not what it trains).
BOOKKEEPING_KEYS = ("train.log_every", "train.checkpoint_every", "train.keep_checkpoints", "train.grad_norm_every",
                    *EVAL_KEYS)


# The layout of the saved TrainState. 1: observations, info and the replay's rollouts as
# dicts with one `done` flag; 2: typed, with `terminated` and `truncated` apart; 3: the
# environment's info counts the observations in a row that showed the goal; 4: the
# environment's state holds each environment's `mjx.Data`.
FORMAT = 4
DATA_FORMAT = 4  # the first format whose environment state holds its mjx.Data
DERIVED = "derived"  # an upgraded state's leaves that the environment recomputes (`NavEnv.with_data`)

# Keys that did not exist when some runs were written, with the value that reproduces
# how those runs behaved. A run's saved configuration that lacks one of them takes it.
LEGACY_VALUES = {
    "env.success_heading_deg": 180.0,  # image goals: position only
    "env.view_fraction": 0.0,  # room and object goals: position only
}


class CheckpointError(UserError, RuntimeError):
    """A checkpoint that is missing, unreadable or written under another configuration."""


def config_differences(a: Config, b: Config, ignore=BOOKKEEPING_KEYS) -> list[str]:
    """'key: a_value != b_value' for every key where the two configurations differ."""
    fa, fb = flat(to_dict(a)), flat(to_dict(b))
    return [f"{k}: {fa[k]!r} != {fb[k]!r}" for k in fa if k not in ignore and fa[k] != fb[k]]


def read_run_config(workdir: str | os.PathLike) -> Config:
    """The configuration saved in a work directory."""
    path = Path(workdir) / CONFIG_FILE
    if not path.exists():
        raise CheckpointError(f"{workdir}: no {CONFIG_FILE}; is this a training work directory?")
    try:
        text = yaml.safe_load(path.read_text()) or {}
        return load_config(path, [f"{k}={v}" for k, v in LEGACY_VALUES.items() if not _has_key(text, k)])
    except (ConfigError, yaml.YAMLError) as e:
        raise CheckpointError(f"{path}: cannot be read as a configuration: {e}") from None


class Checkpointer:
    """Saves and restores the `TrainState` of a run in `workdir/checkpoints`."""

    def __init__(self, workdir: str | os.PathLike, keep: int = 3, create: bool = True):
        self.workdir = Path(workdir).absolute()
        self.directory = self.workdir / CHECKPOINT_DIR
        if not create and not self.directory.is_dir():
            raise CheckpointError(f"{self.workdir}: no checkpoints (missing {CHECKPOINT_DIR}/)")
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=create, enable_async_checkpointing=False)
        self.manager = ocp.CheckpointManager(self.directory, options=options)

    def steps(self) -> list[int]:
        return list(self.manager.all_steps())

    def latest(self) -> Optional[int]:
        return self.manager.latest_step()

    def last_complete(self) -> str:
        """'the last complete checkpoint is ...', for error messages."""
        steps = sorted(self.steps())
        if not steps:
            return f"there is no complete checkpoint in {self.directory}"
        return f"the last complete checkpoint is update {steps[-1]} ({self.directory / str(steps[-1])})"

    def save(self, state, cfg: Config, frames: int) -> int:
        """Write `state` under its update count; returns that count. A write that fails
        (a full disk included) leaves nothing half-written and raises a `CheckpointError`
        that names the last complete checkpoint."""
        step = int(jax.device_get(state.update))
        if step in self.steps():
            return step
        self._check_space(state, step)
        meta = {"update": step, "frames": int(frames), "config": to_dict(cfg), "format": FORMAT}
        quiet_abandoned_io()
        try:
            if jax.process_index() == 0:  # with several processes, one writes the shared files
                save_config(cfg, self.workdir / CONFIG_FILE)
            self.manager.save(
                step,
                args=ocp.args.Composite(state=ocp.args.StandardSave(_drop_empty(state)), meta=ocp.args.JsonSave(meta)),
                force=True,
            )
            self.manager.wait_until_finished()
        except Exception as e:  # noqa: BLE001 - orbax and tensorstore raise many kinds
            self._failed = True
            for partial in self.directory.glob(f"{step}{PARTIAL}*"):
                shutil.rmtree(partial, ignore_errors=True)
            raise CheckpointError(f"cannot write the checkpoint of update {step} to {self.directory}: "
                                  f"{io_reason(e)}; {self.last_complete()}") from None
        return step

    def _check_space(self, state, step: int) -> None:
        """Refuse a write the disk has no room for (`CheckpointError`) before it starts:
        room for the latest checkpoint's size again, or the state's size before the first."""
        try:
            free = shutil.disk_usage(self.directory).free
        except OSError:
            return
        latest = self.latest()
        need = _du(self.directory / str(latest)) if latest is not None else _tree_bytes(state)
        if need > free:
            raise CheckpointError(
                f"cannot write the checkpoint of update {step} to {self.directory}: No space left on device "
                f"(it needs about {_mib(need)}, {_mib(free)} is free); {self.last_complete()}")

    def remove_partial(self, log) -> list[Path]:
        """Remove what checkpoint writes that did not finish left behind (a killed run, a
        full disk), saying so with `log`. Only the run that holds the work directory's lock
        may call it: another run's write in progress looks the same."""
        removed = sorted(p for p in self.directory.glob(f"*{PARTIAL}*") if p.is_dir())
        for partial in removed:
            shutil.rmtree(partial, ignore_errors=True)
            log(f"removed {partial}, a checkpoint whose write did not finish")
        if removed:
            self.manager.reload()
        return removed

    def discard_after(self, step: int, log) -> list[int]:
        """Delete the checkpoints after update `step` (the run goes on from `step`: they
        belong to a past the run no longer has), saying so with `log`."""
        later = sorted(s for s in self.steps() if s > step)
        for s in later:
            try:
                self.manager.delete(s)
            except Exception:  # noqa: BLE001 - a damaged checkpoint: remove its files directly
                shutil.rmtree(self.directory / str(s), ignore_errors=True)
        if later:
            self.manager.reload()
            log(f"removed the checkpoints after update {step} (update{'s' if len(later) > 1 else ''} "
                f"{', '.join(map(str, later))}): the run goes on from update {step}")
        return later

    def restore(self, template, cfg: Optional[Config] = None, step: Optional[int] = None):
        """(state, meta) of checkpoint `step` (default: the latest), shaped like `template`.

        `template` is a `TrainState` (or its `jax.eval_shape`) of the configuration the
        run uses now; with `cfg` given, a checkpoint written under a different
        configuration is refused. A checkpoint that cannot be read is a `CheckpointError`
        that names the checkpoints that can.
        """
        return self._naming_intact(self._restore, template, cfg, step)

    def _restore(self, template, cfg, step):
        step, path, meta = self._checked_meta(cfg, step)
        abstract = _with_sharding(template)
        written = meta.get("format", 1)
        if written == FORMAT:
            state = _fill_empty(abstract, self._restore_state(path, step, ocp.args.StandardRestore(_drop_empty(abstract))))
        else:  # an earlier layout: read it as it was written, bring it up to date, reshape it
            raw = self._restore_state(path, step, ocp.args.StandardRestore())
            for upgrade in UPGRADES[written - 1 : FORMAT - 1]:
                raw = upgrade(raw, from_dict(Config, with_legacy_values(meta["config"])))
            state = _shaped_like(path, abstract, raw)
        self._check_shapes(path, abstract, state)
        return state, meta

    def restore_params(self, template, cfg: Optional[Config] = None, step: Optional[int] = None):
        """(params, meta): only the network parameters of checkpoint `step`, shaped like
        `template` (e.g. `jax.eval_shape(networks.init, key)`); the optimiser state
        and replay buffer stay on disk."""
        return self._naming_intact(self._restore_params, template, cfg, step)

    def _naming_intact(self, read, template, cfg, step):
        """`read(template, cfg, step)`; when the checkpoint cannot be read, the error also
        names the other checkpoints that `read` can read."""
        try:
            return read(template, cfg, step)
        except _Unreadable as e:
            failed = self.resolve_step(step)
            intact = []
            for other in sorted((s for s in self.steps() if s != failed), reverse=True):
                try:
                    read(template, cfg, other)
                    intact.append(other)
                except CheckpointError:
                    pass
            if len(intact) > 1:
                more = (f"; the intact checkpoints are updates {', '.join(map(str, sorted(intact)))}: "
                        f"--step {intact[0]} uses the newest of them")
            elif intact:
                more = f"; the intact checkpoint is update {intact[0]}: --step {intact[0]} uses it"
            else:
                more = "; no other checkpoint can be read either" if len(self.steps()) > 1 else ""
            if intact and intact[0] < failed:
                more += " (the updates after it are lost)"
            raise CheckpointError(f"{e}{more}") from None

    def _restore_params(self, template, cfg, step):
        step, path, meta = self._checked_meta(cfg, step)
        abstract = {"params": _with_sharding(template)}
        params = self._restore_state(path, step, ocp.args.PyTreeRestore(item=abstract, partial_restore=True))["params"]
        self._check_shapes(path, abstract["params"], params)
        return params, meta

    def resolve_step(self, step: Optional[int] = None) -> int:
        """`step` if a checkpoint was written at that update, the latest one if None;
        `CheckpointError` otherwise."""
        steps = sorted(self.steps())
        if not steps:
            raise CheckpointError(f"{self.workdir}: no checkpoint found in {self.directory}")
        if step is None:
            return steps[-1]
        if step not in steps:
            raise CheckpointError(f"{self.workdir}: no checkpoint at update {step}; available: {steps}")
        return step

    def _checked_meta(self, cfg: Optional[Config], step: Optional[int]):
        step = self.resolve_step(step)
        path = self.directory / str(step)
        try:
            meta = self.manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
        except Exception as e:  # noqa: BLE001 - orbax raises many kinds
            raise _Unreadable(f"{path}: cannot read the checkpoint record ({type(e).__name__}: {_short(str(e))})") from None
        if cfg is not None:
            try:
                saved = from_dict(Config, with_legacy_values(meta["config"]))
            except (ConfigError, KeyError, TypeError) as e:
                raise CheckpointError(f"{path}: its configuration is invalid: {e}") from None
            diff = config_differences(saved, cfg)
            if diff:
                raise CheckpointError(
                    f"{path} was written with a different configuration:\n  " + "\n  ".join(diff)
                    + "\nResume with the run's own configuration (omit --config/--set) or start a new work directory."
                )
        return step, path, meta

    def _restore_state(self, path, step: int, args):
        previous_hook = sys.unraisablehook
        sys.unraisablehook = _skip_closed_loop_errors(previous_hook)
        # Before the restore, not after it fails: a read that fails early can be collected, and
        # reported, while the restore is still running.
        silence_abandoned_reads()
        try:
            with warnings.catch_warnings():  # orbax warns that no sharding was given: arrays go to the default device
                warnings.simplefilter("ignore", UserWarning)
                restored = self.manager.restore(step, args=ocp.args.Composite(state=args))
            sys.unraisablehook = previous_hook
        except Exception as e:  # noqa: BLE001
            # The hook stays: reads abandoned by the failed restore may still finish later.
            quiet_abandoned_io()
            raise _Unreadable(
                f"{path}: the checkpoint is corrupt or does not match this configuration "
                f"({type(e).__name__}: {_short(str(e))})"
            ) from None
        return restored["state"]

    @staticmethod
    def _check_shapes(path, abstract, restored) -> None:
        paths = jax.tree_util.tree_flatten_with_path(abstract)[0]
        leaves = jax.tree_util.tree_leaves(restored)
        bad = [jax.tree_util.keystr(p) for (p, want), got in zip(paths, leaves) if np.shape(got) != want.shape]
        if bad:
            raise CheckpointError(f"{path}: array shapes do not match this configuration at {', '.join(bad[:5])}")

    def close(self):
        try:
            self.manager.close()
        except Exception:  # noqa: BLE001
            if not getattr(self, "_failed", False):
                raise  # after a failed write, the error already raised is the one to report


class _Unreadable(CheckpointError):
    """A checkpoint whose files cannot be read (damaged, truncated, missing)."""


def io_reason(e: BaseException) -> str:
    """What went wrong in a failed write, in a few words: the OS error's text where there is
    one in the exception's chain (tensorstore's errors carry it as text), else the error."""
    seen = e
    while seen is not None:
        if isinstance(seen, OSError) and seen.strerror:
            return seen.strerror + (" (the disk is full)" if seen.errno == errno.ENOSPC else "")
        seen = seen.__cause__ or seen.__context__
    text = str(e)
    if "No space left on device" in text or "os_error_code='28'" in text:
        return "No space left on device (the disk is full)"
    return f"{type(e).__name__}: {_short(text)}"


def _du(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def _tree_bytes(tree) -> int:
    return sum(int(np.prod(np.shape(x))) * np.dtype(x.dtype).itemsize for x in jax.tree_util.tree_leaves(tree))


def _mib(n: int) -> str:
    return f"{n / 2**20:.1f} MiB" if n < 2**30 else f"{n / 2**30:.1f} GiB"


def _upgrade_to_2(state: dict, cfg: Config) -> dict:
    """Format 1 -> 2: the observation gains the target's index; `done` splits into
    `terminated` (the step reached the goal: its reward is 1) and `truncated` (a time-out)."""
    env = state["env_state"]
    info, metrics = env["info"], env["metrics"]
    env["obs"]["target_index"] = (np.asarray(info["scene"]) * cfg.env.goals_per_scene + np.asarray(info["goal"])).astype(np.int32)
    done = np.asarray(env.pop("done"))
    env["terminated"] = done & np.asarray(metrics["success"])
    env["truncated"] = done & np.asarray(metrics["truncated"])
    if state.get("replay"):
        data = state["replay"]["data"]
        done, reward = np.asarray(data.pop("done")), np.asarray(data["reward"])
        data["terminated"], data["truncated"] = done & (reward != 0), done & (reward == 0)
    return state


def _upgrade_to_3(state: dict, cfg: Config) -> dict:
    """Format 2 -> 3: the environment's info gains the view streak (zero: the runs that
    wrote format 2 had no view criterion)."""
    info = state["env_state"]["info"]
    info["view_streak"] = np.zeros_like(np.asarray(info["step"]))
    return state


def _upgrade_to_4(state: dict, cfg: Config) -> dict:
    """Format 3 -> 4: the environment's state gains its `mjx.Data`, a function of each
    agent's scene and pose in the static scenes of those runs: left to the environment to
    recompute after the restore (`NavEnv.with_data`)."""
    state["env_state"]["data"] = DERIVED
    return state


UPGRADES = (_upgrade_to_2, _upgrade_to_3, _upgrade_to_4)  # UPGRADES[k] brings format k + 1 to k + 2


def _has_key(tree, dotted: str) -> bool:
    for part in dotted.split("."):
        if not isinstance(tree, dict) or part not in tree:
            return False
        tree = tree[part]
    return True


def with_legacy_values(config: dict) -> dict:
    """A saved configuration (nested dict) with the keys it lacks from `LEGACY_VALUES`."""
    config = copy.deepcopy(config)
    for dotted, value in LEGACY_VALUES.items():
        if not _has_key(config, dotted):
            *parents, name = dotted.split(".")
            node = config
            for p in parents:
                node = node.setdefault(p, {})
            node[name] = value
    return config


def _with_sharding(template):
    """The abstract arrays of `template`, each with a sharding: its own, or this process's
    first device. Orbax restores into them whatever layout the checkpoint was written
    from (one device, several, several processes)."""
    here = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])

    def leaf(x):
        x = ocp.utils.to_shape_dtype_struct(x)
        return x if getattr(x, "sharding", None) is not None else jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=here)

    return jax.tree_util.tree_map(leaf, template)


def _drop_empty(tree):
    """`tree` with its zero-size arrays (which orbax does not write; e.g. the joint
    positions of a scene without joints in each environment's `mjx.Data`) left out."""
    return jax.tree_util.tree_map(lambda a: None if np.prod(np.shape(a)) == 0 else a, tree)


def _fill_empty(template, restored):
    """The tree of `template` with the leaves of `restored` (`template` after
    `_drop_empty`) and zero-size arrays where `_drop_empty` left them out."""
    kept = iter(jax.tree_util.tree_leaves(restored))
    leaves = [jax.numpy.zeros(t.shape, t.dtype) if np.prod(t.shape) == 0 else next(kept)
              for t in jax.tree_util.tree_leaves(template)]
    return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(template), leaves)


def _shaped_like(path, abstract, raw):
    """The tree of `abstract` with each leaf taken from the nested dicts and lists `raw`
    (as orbax reads a checkpoint without a target) at the same keys."""

    def take(key_path, want):
        node = raw
        for k in key_path:
            if isinstance(node, str) and node == DERIVED:
                return jax.numpy.zeros(want.shape, want.dtype)
            name = getattr(k, "name", getattr(k, "key", getattr(k, "idx", None)))
            try:
                node = node[name]
            except (KeyError, IndexError, TypeError):
                raise CheckpointError(f"{path}: the checkpoint has no {jax.tree_util.keystr(key_path)}") from None
        return jax.numpy.asarray(node, want.dtype)

    return jax.tree_util.tree_map_with_path(take, abstract)


def _skip_closed_loop_errors(previous):
    """An unraisable-exception hook that drops the 'Event loop is closed' errors of array
    reads that a failed orbax restore left running, and passes everything else on."""

    def hook(unraisable):
        exc = unraisable.exc_value
        if isinstance(exc, RuntimeError) and str(exc) == "Event loop is closed":
            return
        previous(unraisable)

    return hook


def silence_abandoned_reads() -> None:
    """For an orbax restore: when one of its asynchronous reads fails, the others are abandoned,
    and Python reports each when it is collected, often at exit, as a "coroutine ... was never awaited"
    warning or an asyncio "Task exception was never retrieved" traceback raised in orbax.
    Drop those reports, so that the restore's error is all a user sees."""
    warnings.filterwarnings("ignore", message=r"coroutine .* was never awaited", category=RuntimeWarning)
    asyncio_log = logging.getLogger("asyncio")
    if not any(isinstance(f, _AbandonedOrbaxTasks) for f in asyncio_log.filters):
        asyncio_log.addFilter(_AbandonedOrbaxTasks())


class _AbandonedOrbaxTasks:
    """A logging filter: drops "Task (or Future) exception was never retrieved" records of
    orbax tasks: those whose traceback passes through orbax, or whose task (its repr, in
    the message, names the file its coroutine is defined in) is orbax's or tensorstore's."""

    def filter(self, record) -> bool:
        message = record.getMessage()
        if not message.startswith(("Task exception was never retrieved", "Future exception was never retrieved")):
            return True
        if "orbax" in message or "tensorstore" in message:
            return False
        return not (record.exc_info and _through_orbax(record.exc_info[2]))


def _through_orbax(tb) -> bool:
    while tb is not None:
        if "orbax" in tb.tb_frame.f_code.co_filename:
            return True
        tb = tb.tb_next
    return False


def quiet_abandoned_io() -> None:
    """For an orbax save or a failed restore: when a write fails (a full disk) or a read
    does (a damaged checkpoint), orbax's threads log the error, and the asynchronous
    reads and writes it abandons report theirs as they finish or are collected (often at
    exit). `Checkpointer` turns the error into one line; drop those reports (only
    orbax's), so that the line is all a user sees."""
    silence_abandoned_reads()
    absl_log = logging.getLogger("absl")
    if not any(isinstance(f, _OrbaxThreadErrors) for f in absl_log.filters):
        absl_log.addFilter(_OrbaxThreadErrors())
    if not isinstance(sys.unraisablehook, _SkipOrbaxLeftovers):
        sys.unraisablehook = _SkipOrbaxLeftovers(sys.unraisablehook)


class _OrbaxThreadErrors:
    """A logging filter: drops orbax's log of an exception in one of its threads (the save
    raises it again)."""

    def filter(self, record) -> bool:
        return not ("orbax" in record.pathname and "raised an exception" in record.getMessage())


class _SkipOrbaxLeftovers:
    """An unraisable-exception hook that drops the errors of orbax's abandoned writes
    (coroutines collected unfinished, callbacks into a closed event loop) and passes
    everything else on."""

    def __init__(self, previous):
        self.previous = previous

    def __call__(self, unraisable):
        exc, obj = unraisable.exc_value, unraisable.object
        code = getattr(obj, "cr_code", None)
        if (isinstance(exc, RuntimeError) and str(exc) == "Event loop is closed") or (
                code is not None and "orbax" in code.co_filename) or _through_orbax(unraisable.exc_traceback):
            return
        self.previous(unraisable)


def _short(message: str, limit: int = 300) -> str:
    """The first line of an error message, at most `limit` characters."""
    line = message.strip().splitlines()[0] if message.strip() else ""
    line = line.split(" See full TensorStore details")[0]  # tensorstore's spec of the array follows
    return line if len(line) <= limit else line[: limit - 3] + "..."

