"""Restore a trained run to act: its configuration at evaluation settings, an environment
in its training houses, in held-out houses or with new targets, and its parameters.

Only the parameters are read from the checkpoint (not the optimiser state or the
replay buffer). `eval_config` refuses overrides of keys the network's shapes depend on.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import jax

from a2catvn_jax.agent.networks import make_networks
from a2catvn_jax.config import ConfigError, apply_overrides
from a2catvn_jax.env import NavEnv
from a2catvn_jax.env.world import World, make_scenes
from a2catvn_jax.run.checkpoint import Checkpointer, CheckpointError, config_differences, read_run_config

HELD_OUT_OFFSET = 1_000_003  # scene seed offset of held-out houses
NEW_TARGETS_OFFSET = 2_000_029  # goal seed offset of new targets in the training houses
HOUSES = ("train", "held-out", "new-targets")
# Keys the network's shapes depend on ("agent." is the whole section).
NETWORK_KEYS = ("agent.", "env.render.image_size", "env.action_set", "train.pixel_control_cell", "train.aux_downsize")


def eval_config(run_cfg, overrides: Sequence[str] = ()):
    """The run's configuration at complexity 1 with `overrides`; `ConfigError` if they change the network."""
    base = apply_overrides(run_cfg, ["env.complexity=1.0"])
    cfg = apply_overrides(base, list(overrides))
    refused = []
    for diff in config_differences(base, cfg, ignore=()):
        key, values = diff.split(": ", 1)
        if any(key == k or (k.endswith(".") and key.startswith(k)) for k in NETWORK_KEYS):
            run_value, given = values.split(" != ", 1)
            refused.append((key, f"{key}: the network depends on it; evaluation keeps the run's value {run_value} "
                                 f"(given {given})"))
    if refused:
        raise ConfigError("; ".join(message for _, message in refused), key=refused[0][0])
    return cfg


def make_env(env_cfg, houses: str = "train") -> NavEnv:
    """A `NavEnv` in the run's training houses, in held-out houses generated with offset
    seeds, or in the training houses with new goals ("new-targets")."""
    if houses not in HOUSES:
        raise ValueError(f"houses must be one of {HOUSES}, got {houses!r}")
    if houses == "held-out" and env_cfg.scene.kind == "mjcf":
        raise ValueError("held-out houses need generated scenes; env.scene.kind is 'mjcf' (one fixed file)")
    if houses == "new-targets":
        world = World(env_cfg, make_scenes(env_cfg), seed=env_cfg.scene.seed + NEW_TARGETS_OFFSET)
        return NavEnv(env_cfg, world=world)
    return NavEnv(env_cfg, seed_offset=0 if houses == "train" else HELD_OUT_OFFSET)


def restore(workdir, step: Optional[int] = None, houses: str = "train", overrides: Sequence[str] = (),
            log: Callable[[str], None] = lambda _: None):
    """Checkpoint `step` (default: the latest) of the run in `workdir`, ready to act in `houses`.

    Returns (cfg, run_cfg, env, networks, params, step, meta): the evaluation configuration
    (the run's at complexity 1 with `overrides`), the run's own, the environment, the
    network, its parameters, the update restored and the checkpoint's metadata.
    """
    if houses not in HOUSES:
        raise ValueError(f"houses must be one of {HOUSES}, got {houses!r}")
    workdir = Path(workdir)
    if not workdir.is_dir():
        raise CheckpointError(f"{workdir}: no such directory")
    run_cfg = read_run_config(workdir)
    cfg = eval_config(run_cfg, overrides)

    ckpt = Checkpointer(workdir, create=False)
    try:
        step = ckpt.resolve_step(step)
        t0 = time.perf_counter()
        env = make_env(cfg.env, houses)
        log(f"built {env.num_scenes} {houses} scene(s) in {time.perf_counter() - t0:.1f} s")
        # Only the parameters are read (not the optimiser state or the replay buffer).
        networks = make_networks(cfg, env.num_actions)
        params, meta = ckpt.restore_params(jax.eval_shape(networks.init, jax.random.PRNGKey(0)), run_cfg, step)
    finally:
        ckpt.close()
    log(f"restored update {step} ({meta['frames']:,} training frames) from {ckpt.directory}")
    return cfg, run_cfg, env, networks, params, step, meta
