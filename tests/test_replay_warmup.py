"""`train.replay_warmup`: the replay buffer filled before the first update.

The initial state holds `replay_size // rollout_length - 1` rollouts of the initial
policy and nothing else moves that learning owns (parameters, optimiser state, update
count, so frames, learning rate and curriculum); the first update's rollout fills the
buffer; a run resumed from its checkpoints equals one run straight through; the setting
does nothing without a replay loss.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

from a2catvn_jax.agent import update as update_lib
from a2catvn_jax.agent.networks import make_networks
from a2catvn_jax.config import load_config
from a2catvn_jax.env import make_env
from a2catvn_jax.run.logger import read_jsonl
from a2catvn_jax.run.training import train
from tiny import TINY_SYNTHETIC

TINY = TINY_SYNTHETIC + [
    "train.replay_size=16",  # 4 rollouts of 4 steps
    "train.log_every=1",
    "train.checkpoint_every=2",
]
WARM = ["train.replay_warmup=true"]
NO_REPLAY = ["train.loss_weights.pixel_control=0", "train.loss_weights.reward_prediction=0",
             "train.loss_weights.off_policy_critic=0"]


def _leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(jax.device_get(tree))]


def _same(a, b):
    return len(_leaves(a)) == len(_leaves(b)) and all(np.array_equal(x, y) for x, y in zip(_leaves(a), _leaves(b)))


def _equal_in_float32(a, b):
    """Equal up to float32 rounding: two compiled programs (the warm and the cold init)
    need not round alike; a step of learning would move the parameters far more."""
    return len(_leaves(a)) == len(_leaves(b)) and all(
        np.allclose(x, y, rtol=1e-5, atol=1e-7) for x, y in zip(_leaves(a), _leaves(b)))


@pytest.fixture(scope="module")
def built():
    cfg = load_config(None, TINY + WARM)
    env = make_env(cfg.env)
    return env, make_networks(cfg, env.num_actions)


def _fns(built, *extra):
    env, net = built
    cfg = load_config(None, TINY + list(extra))
    return cfg, update_lib.make_update(env, net, cfg)


def test_warmup_fills_the_buffer_and_nothing_that_learning_owns(built):
    cfg, warm = _fns(built, *WARM)
    _, cold = _fns(built)
    slots = cfg.train.replay_size // cfg.train.rollout_length
    assert update_lib.warmup_rollouts(cfg) == slots - 1 == 3
    key = jax.random.PRNGKey(0)
    ts, ts0 = warm.init(key), cold.init(key)
    assert int(ts.replay.count) == slots - 1 and int(ts0.replay.count) == 0
    assert int(ts.update) == 0
    assert _equal_in_float32(ts.params, ts0.params) and _equal_in_float32(ts.opt_state, ts0.opt_state)
    assert not _same(ts.env_state, ts0.env_state) and not _same(ts.key, ts0.key)
    # Each warm-up rollout continues from the last: stored rollouts start where the previous one ended.
    data = jax.device_get(ts.replay.data)
    for k in range(slots - 2):
        np.testing.assert_array_equal(data.rgb[k, -1], data.rgb[k + 1, 0])

    ts1, metrics = warm.update(ts)
    assert int(ts1.replay.count) == slots and bool(np.all(np.asarray(update_lib.replay_lib.filled(ts1.replay))))
    assert int(ts1.update) == 1
    np.testing.assert_allclose(float(metrics["learning_rate"]), cfg.train.learning_rate, rtol=1e-6)
    assert np.isfinite(float(metrics["loss/total"]))


def test_warmup_without_a_replay_loss_does_nothing(built):
    cfg, warm = _fns(built, *WARM, *NO_REPLAY)
    _, cold = _fns(built, *NO_REPLAY)
    assert update_lib.warmup_rollouts(cfg) == 0
    key = jax.random.PRNGKey(1)
    ts, ts0 = warm.init(key), cold.init(key)
    assert ts.replay is None and _same(ts, ts0)


def test_resume_with_warmup_is_exact_and_frames_exclude_it(tmp_path):
    cfg = load_config(None, TINY + WARM)
    quiet = dict(progress=False, log=lambda *_: None)
    _, straight, _ = train(cfg, tmp_path / "straight", max_updates=4, **quiet)
    train(cfg, tmp_path / "resumed", max_updates=2, **quiet)
    _, resumed, _ = train(cfg, tmp_path / "resumed", resume=True, max_updates=2, **quiet)
    assert _same(resumed, straight)
    rows = read_jsonl(tmp_path / "straight" / "metrics.jsonl")
    per_update = update_lib.frames_per_update(cfg)
    assert [r["frames"] for r in rows] == [u * per_update for u in range(1, 5)]
    assert rows[0]["learning_rate"] == pytest.approx(cfg.train.learning_rate, rel=1e-6)
