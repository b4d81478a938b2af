"""The environment's contract: the world is data, time-outs are kept apart from terminal
states, observation and info are typed.

- One jitted step serves worlds of one shape: the training houses, held-out houses and
  new targets padded to common shapes (`make_envs`) run through one compiled step, and
  each gives what an environment built for it alone gives.
- A world padded to another's shapes renders and steps exactly as before padding.
- `truncated` marks exactly the time-outs, `terminated` exactly the successes.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from a2catvn_jax.config import load_config
from a2catvn_jax.env import Info, NavEnv, Observation
from a2catvn_jax.run.restore import house_env, make_envs

CFG = [
    "env.num_envs=6",
    "env.render.image_size=16",
    "env.render.culling=false",
    "env.scene.num_scenes=2",
    "env.scene.grid=[1,2]",
    "env.goals_per_scene=2",
]


def _leaves_equal(a, b) -> bool:
    return all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in
               zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))


@pytest.fixture(scope="module")
def envs():
    cfg = load_config(None, CFG).env
    envs = make_envs(cfg)
    return cfg, envs["train"], envs["held-out"], envs["new-targets"]


@pytest.fixture(scope="module")
def stepped(envs):
    """reset + 5 random steps, one jitted function taking the world as data."""
    cfg, train, _, _ = envs

    @jax.jit
    def run(world, key):
        state = train.reset(key, world=world)
        for k in jax.random.split(key, 5):
            state = train.step(state, jax.random.randint(k, (cfg.num_envs,), 0, train.num_actions), world)
        return state

    return run


def test_one_compile_serves_worlds_of_one_shape(envs, stepped):
    cfg, train, held_out, new_targets = envs
    assert held_out.world.arrays.fits(train.world.arrays) and train.world.arrays.fits(held_out.world.arrays)
    key = jax.random.PRNGKey(0)
    results = {name: stepped(e.world.arrays, key) for name, e in
               (("train", train), ("held-out", held_out), ("new-targets", new_targets))}
    assert stepped._cache_size() == 1
    # Each world's result is the one its own environment gives with its own (unpadded) world.
    own = house_env(cfg, "held-out")
    assert not all(a.shape == b.shape for a, b in zip(jax.tree_util.tree_leaves(own.world.arrays),
                                                      jax.tree_util.tree_leaves(held_out.world.arrays)))
    state = stepped(own.world.arrays, key)  # compiled again, for the unpadded shapes
    assert _leaves_equal(state.obs, results["held-out"].obs)
    assert _leaves_equal(state.info, results["held-out"].info)
    # The three worlds differ: other houses, other targets.
    assert not np.array_equal(np.asarray(results["train"].obs.rgb), np.asarray(results["held-out"].obs.rgb))
    assert not np.array_equal(np.asarray(results["train"].obs.target_rgb), np.asarray(results["new-targets"].obs.target_rgb))
    assert [s.name for s in new_targets.world.scenes] == [s.name for s in train.world.scenes]


def test_padding_changes_nothing(envs, stepped):
    """The training world padded to the common shapes steps exactly as the unpadded one."""
    cfg, train, _, _ = envs
    own = house_env(cfg, "train")
    padded, plain = train.world.arrays, own.world.arrays
    assert plain.fits(padded) and not padded.fits(plain)  # padded along some axis
    key = jax.random.PRNGKey(3)
    a, b = stepped(plain, key), stepped(padded, key)
    assert _leaves_equal(a.obs, b.obs) and _leaves_equal(a.info, b.info)
    np.testing.assert_array_equal(np.asarray(a.done), np.asarray(b.done))


def test_time_outs_are_apart_from_terminal_states():
    cfg = load_config(None, CFG + ["env.max_episode_steps=3", "env.success_distance=3.0", "env.success_heading_deg=180"]).env
    env = NavEnv(cfg)
    state = jax.jit(env.reset)(jax.random.PRNGKey(1))
    assert isinstance(state.obs, Observation) and isinstance(state.info, Info)
    assert {f.name for f in dataclasses.fields(Info)} >= {"scene", "goal", "pose", "step", "key"}
    step = jax.jit(env.step)
    seen_truncated = seen_terminated = False
    for k in jax.random.split(jax.random.PRNGKey(2), 12):
        before = state.info.step
        state = step(state, jax.random.randint(k, (cfg.num_envs,), 0, env.num_actions))
        term, trunc = np.asarray(state.terminated), np.asarray(state.truncated)
        np.testing.assert_array_equal(term, np.asarray(state.metrics["success"]))
        np.testing.assert_array_equal(trunc, np.asarray(state.metrics["truncated"]))
        np.testing.assert_array_equal(np.asarray(state.done), term | trunc)
        assert not np.any(term & trunc)
        np.testing.assert_array_equal(trunc, (np.asarray(before) + 1 >= 3) & ~term)
        np.testing.assert_array_equal(np.asarray(state.reward), term.astype(np.float32))
        seen_truncated |= trunc.any()
        seen_terminated |= term.any()
    assert seen_truncated and seen_terminated
