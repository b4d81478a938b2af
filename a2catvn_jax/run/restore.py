"""Restore a trained run to act: its configuration at evaluation settings, its network
and parameters, and environments in its training houses, in held-out houses or with
new targets.

Only the parameters are read from the checkpoint (not the optimiser state or the
replay buffer). `eval_config` refuses overrides of keys the network's shapes depend on.
`make_envs` pads the worlds of several house sets to common shapes, so functions
compiled for one take the others' worlds as data (`NavEnv.step(..., world=...)`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable, Optional, Sequence

import jax

from a2catvn_jax.agent.networks import Networks, Params, make_networks
from a2catvn_jax.config import HOUSES, Config, ConfigError, apply_overrides
from a2catvn_jax.env import NavEnv, World, action_names, require_world
from a2catvn_jax.env.scenes import mjcf
from a2catvn_jax.env.world import make_scenes, share_shapes
from a2catvn_jax.run.checkpoint import Checkpointer, CheckpointError, config_differences, read_run_config

HELD_OUT_OFFSET = 1_000_003  # scene seed offset of held-out houses
NEW_TARGETS_OFFSET = 2_000_029  # goal seed offset of new targets in the training houses
# Keys the network's shapes depend on ("agent." is the whole section) ...
NETWORK_KEYS = ("agent.", "env.render.image_size", "env.action_set", "train.pixel_control_cell", "train.aux_downsize")
# ... but for what the trained network is shown: `agent.blind` at evaluation zeroes the
# target images or the observations of a network trained with them (what does it use?).
INPUT_KEYS = ("agent.blind",)


@dataclasses.dataclass
class Restored:
    """A run's checkpoint, ready to act: the evaluation configuration (the run's at
    complexity 1 with the overrides), the run's own, the network, its parameters, the
    update restored, its training frames and the checkpoint's record."""

    workdir: Path
    cfg: Config
    run_cfg: Config
    networks: Networks
    params: Params
    step: int
    frames: int
    meta: dict


def eval_config(run_cfg, overrides: Sequence[str] = ()):
    """The run's configuration at complexity 1 with `overrides`; `ConfigError` if they change the
    network (`agent.blind`, what it is shown, may change: `INPUT_KEYS`)."""
    base = apply_overrides(run_cfg, ["env.complexity=1.0"])
    cfg = apply_overrides(base, list(overrides))
    refused = []
    for diff in config_differences(base, cfg, ignore=()):
        key, values = diff.split(": ", 1)
        if key not in INPUT_KEYS and any(key == k or (k.endswith(".") and key.startswith(k)) for k in NETWORK_KEYS):
            run_value, given = values.split(" != ", 1)
            refused.append((key, f"{key}: the network depends on it; evaluation keeps the run's value {run_value} "
                                 f"(given {given})"))
    if refused:
        raise ConfigError("; ".join(message for _, message in refused), key=refused[0][0])
    return cfg


def check_houses(*houses: str) -> None:
    """`ValueError` unless every name is one of `HOUSES`."""
    for h in houses:
        if h not in HOUSES:
            raise ValueError(f"houses must be one of {HOUSES}, got {h!r}")


def _scenes(env_cfg, houses: str, scenes: Optional[list] = None) -> tuple[list, int]:
    """(scenes, goal seed) of a set of houses; `scenes`: the training houses when built."""
    check_houses(houses)
    if houses == "held-out" and env_cfg.scene.kind == "mjcf":
        raise ValueError("held-out houses need generated scenes; env.scene.kind is 'mjcf' (one fixed file)")
    if houses == "held-out":
        return make_scenes(env_cfg, HELD_OUT_OFFSET), env_cfg.scene.seed + HELD_OUT_OFFSET
    scenes = scenes if scenes is not None else make_scenes(env_cfg)
    return scenes, env_cfg.scene.seed + (NEW_TARGETS_OFFSET if houses == "new-targets" else 0)


def house_env(env_cfg, houses: str = "train", scenes: Optional[list] = None) -> NavEnv:
    """A `NavEnv` in the run's training houses, in held-out houses generated with offset
    seeds, or in the training houses with new goals ("new-targets"). `scenes`: the
    training houses when already built (train and new-targets use them)."""
    require_world(env_cfg, "evaluation")
    scenes, seed = _scenes(env_cfg, houses, scenes)
    return NavEnv(env_cfg, world=World(env_cfg, scenes, seed=seed))


def make_envs(env_cfg, houses=HOUSES) -> dict:
    """houses -> `NavEnv` of each set, built with one geom layout and padded to common
    shapes (`world.share_shapes`) so that they share compiled functions."""
    require_world(env_cfg, "evaluation")
    check_houses(*houses)
    sets, train = {}, None
    for h in houses:
        sets[h] = _scenes(env_cfg, h, train)
        if h != "held-out":
            train = sets[h][0]
    layout = mjcf.layout_of([s for scenes, _ in sets.values() for s in scenes])
    envs = {h: NavEnv(env_cfg, world=World(env_cfg, scenes, seed=seed, layout=layout)) for h, (scenes, seed) in sets.items()}
    share_shapes([e.world for e in envs.values()])
    return envs


@dataclasses.dataclass
class Located:
    """A run's checkpoint that exists, before its parameters are read: its work
    directory, the evaluation and the run's configurations, and the update."""

    workdir: Path
    cfg: Config
    run_cfg: Config
    step: int

    def restore(self, log: Callable[[str], None] = lambda _: None) -> Restored:
        """Read the checkpoint's parameters (`CheckpointError` if they cannot be read)."""
        networks = make_networks(self.cfg, len(action_names(self.cfg.env)))
        ckpt = Checkpointer(self.workdir, create=False)
        try:
            template = jax.eval_shape(networks.init, jax.random.PRNGKey(0))
            params, meta = ckpt.restore_params(template, self.run_cfg, self.step)
        finally:
            ckpt.close()
        log(f"restored update {self.step} ({meta['frames']:,} training frames) from {ckpt.directory}")
        return Restored(self.workdir, self.cfg, self.run_cfg, networks, params, self.step, int(meta["frames"]), meta)


def locate(workdir, step: Optional[int] = None, overrides: Sequence[str] = ()) -> Located:
    """Checkpoint `step` (default: the latest) of the run in `workdir`, checked to exist
    (`CheckpointError`), with the evaluation configuration (`ConfigError` for overrides
    that change the network)."""
    workdir = Path(workdir)
    if not workdir.is_dir():
        raise CheckpointError(f"{workdir}: no such directory")
    run_cfg = read_run_config(workdir)
    cfg = eval_config(run_cfg, overrides)
    ckpt = Checkpointer(workdir, create=False)
    try:
        step = ckpt.resolve_step(step)
    finally:
        ckpt.close()
    return Located(workdir, cfg, run_cfg, step)


def restore(workdir, step: Optional[int] = None, overrides: Sequence[str] = (),
            log: Callable[[str], None] = lambda _: None) -> Restored:
    """The parameters of checkpoint `step` (default: the latest) of the run in `workdir`
    (`locate`, then `Located.restore`)."""
    return locate(workdir, step, overrides).restore(log)
