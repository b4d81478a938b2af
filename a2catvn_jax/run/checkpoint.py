"""Orbax checkpoints of a training run.

A work directory holds `config.yaml` (the run's full configuration) and
`checkpoints/<update>/` written by an orbax `CheckpointManager`: the whole
`TrainState` (parameters, optimiser state, environment and agent state, replay
buffer, PRNG key, update count) and a small JSON record (update, frames, config).
Restoring it and calling `update` continues the run exactly where it stopped.

Every problem is a `CheckpointError` that says what is wrong: no checkpoint in the
directory, a step that does not exist, a checkpoint that cannot be read, or one
written under a different configuration (the differing keys are listed).
"""

from __future__ import annotations

import copy
import logging
import os
import sys
import warnings
from pathlib import Path
from typing import Optional

import jax
import numpy as np
import orbax.checkpoint as ocp
import yaml

from a2catvn_jax.config import Config, ConfigError, from_dict, load_config, save_config, to_dict
from a2catvn_jax.errors import UserError

CONFIG_FILE = "config.yaml"
CHECKPOINT_DIR = "checkpoints"
# Keys that may differ between the run that wrote a checkpoint and the one resuming it.
BOOKKEEPING_KEYS = ("train.log_every", "train.checkpoint_every", "train.keep_checkpoints", "train.grad_norm_every")


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


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else k
        out.update(_flat(v, key) if isinstance(v, dict) else {key: v})
    return out


def config_differences(a: Config, b: Config, ignore=BOOKKEEPING_KEYS) -> list[str]:
    """'key: a_value != b_value' for every key where the two configurations differ."""
    fa, fb = _flat(to_dict(a)), _flat(to_dict(b))
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

    def save(self, state, cfg: Config, frames: int) -> int:
        """Write `state` under its update count; returns that count."""
        step = int(jax.device_get(state.update))
        if step in self.steps():
            return step
        save_config(cfg, self.workdir / CONFIG_FILE)
        meta = {"update": step, "frames": int(frames), "config": to_dict(cfg), "format": FORMAT}
        self.manager.save(
            step,
            args=ocp.args.Composite(state=ocp.args.StandardSave(_drop_empty(state)), meta=ocp.args.JsonSave(meta)),
            force=True,
        )
        self.manager.wait_until_finished()
        return step

    def restore(self, template, cfg: Optional[Config] = None, step: Optional[int] = None):
        """(state, meta) of checkpoint `step` (default: the latest), shaped like `template`.

        `template` is a `TrainState` (or its `jax.eval_shape`) of the configuration the
        run uses now; with `cfg` given, a checkpoint written under a different
        configuration is refused.
        """
        step, path, meta = self._checked_meta(cfg, step)
        abstract = jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, template)
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
        step, path, meta = self._checked_meta(cfg, step)
        abstract = {"params": jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, template)}
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
            raise CheckpointError(f"{path}: cannot read the checkpoint record ({type(e).__name__}: {_short(str(e))})") from None
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
            raise CheckpointError(
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
        self.manager.close()


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
    """A logging filter: drops "Task exception was never retrieved" records of orbax tasks."""

    def filter(self, record) -> bool:
        if not record.getMessage().startswith("Task exception was never retrieved") or not record.exc_info:
            return True
        tb = record.exc_info[2]
        while tb is not None:
            if "orbax" in tb.tb_frame.f_code.co_filename:
                return False
            tb = tb.tb_next
        return True


def _short(message: str, limit: int = 300) -> str:
    """The first line of an error message, at most `limit` characters."""
    line = message.strip().splitlines()[0] if message.strip() else ""
    return line if len(line) <= limit else line[: limit - 3] + "..."

