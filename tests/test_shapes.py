"""Shape, rank and dtype checks at the public boundaries (chex, at trace time): the
environment's step, each loss function and the update's trajectory reject a misshaped
input with a message naming the shapes, instead of broadcasting it into a wrong result."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from a2catvn_jax.agent import losses
from a2catvn_jax.agent.update import transition_example
from a2catvn_jax.config import load_config
from a2catvn_jax.env import NavEnv
from tiny import TINY_LEARNER

T, B, A = 4, 3, 5


def _f(*shape):
    return jnp.zeros(shape, jnp.float32)


def _i(*shape):
    return jnp.zeros(shape, jnp.int32)


def _b(*shape):
    return jnp.zeros(shape, bool)


GOOD = {
    "returns": lambda: losses.bootstrapped_returns(_f(T, B), _b(T, B), _f(B), 0.9, _b(T, B), _f(T, B)),
    "actor_critic": lambda: losses.actor_critic_losses(_f(T, B, A), _f(T, B), _i(T, B), _f(T, B)),
    "off_policy_critic": lambda: losses.off_policy_critic_loss(_f(T + 1, B), _f(T, B), _b(T, B), 0.9),
    "reward_prediction": lambda: losses.reward_prediction_loss(_f(B, 3), _f(B)),
    "pixel_control": lambda: losses.pixel_control_loss(jnp.zeros((T + 1, 8, 8, 3), jnp.uint8), _i(T), _b(T),
                                                       _f(T + 1, 2, 2, A), 0.9, 4),
    "mse": lambda: losses.mse(_f(B, 4, 4), _f(B, 4, 4)),
    "cross_entropy": lambda: losses.cross_entropy(_f(B, 4, 4, 7), _i(B, 4, 4)),
}

BAD = {
    # the bootstrap value of each environment, given per step
    "returns": (lambda: losses.bootstrapped_returns(_f(T, B), _b(T, B), _f(T, B), 0.9), "rank"),
    # values and returns of different lengths (a [T+1] value sequence not cut to T)
    "actor_critic": (lambda: losses.actor_critic_losses(_f(T, B, A), _f(T + 1, B), _i(T, B), _f(T, B)), "shape"),
    # float actions
    "actor_critic_dtype": (lambda: losses.actor_critic_losses(_f(T, B, A), _f(T, B), _f(T, B), _f(T, B)), "type"),
    # values of T states instead of T + 1
    "off_policy_critic": (lambda: losses.off_policy_critic_loss(_f(T, B), _f(T, B), _b(T, B), 0.9), "shape"),
    "reward_prediction": (lambda: losses.reward_prediction_loss(_f(B, 3), _f(B + 1)), "shape"),
    # float images
    "pixel_control": (lambda: losses.pixel_control_loss(_f(T + 1, 8, 8, 3), _i(T), _b(T), _f(T + 1, 2, 2, A), 0.9, 4),
                      "type"),
    # a depth map [B, a, a, 1] against targets [B, a, a] would broadcast to [B, a, a, a]
    "mse": (lambda: losses.mse(_f(B, 4, 4, 1), _f(B, 4, 4)), "shape"),
    "cross_entropy": (lambda: losses.cross_entropy(_f(B, 4, 4, 7), _i(B, 2, 2)), "shape"),
}


@pytest.mark.parametrize("name", sorted(GOOD))
def test_loss_functions_accept_their_documented_shapes(name):
    out = jax.jit(GOOD[name])()
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(out))


@pytest.mark.parametrize("name", sorted(BAD))
def test_loss_functions_reject_misshaped_inputs(name):
    fn, what = BAD[name]
    with pytest.raises(AssertionError, match=rf"(?i)\[Chex\].*{what}"):
        jax.jit(fn)()


def test_trajectory_check_names_the_wrong_field():
    cfg = load_config(None, TINY_LEARNER)
    traj = transition_example(cfg, B)
    size = cfg.env.render.image_size
    traj.check(cfg.train.rollout_length, B, size)
    with pytest.raises(AssertionError, match=r"\[Chex\]"):
        traj.check(cfg.train.rollout_length + 1, B, size)  # T+1 inputs of a longer rollout
    with pytest.raises(AssertionError, match=r"\[Chex\]"):
        traj.replace(rgb=traj.rgb.astype(jnp.float32)).check(cfg.train.rollout_length, B, size)
    with pytest.raises(AssertionError, match=r"\[Chex\]"):
        traj.replace(action=traj.action[:-1]).check(cfg.train.rollout_length, B, size)


def test_environment_step_rejects_actions_of_another_batch_or_dtype():
    cfg = load_config(None, TINY_LEARNER + ["env.scene.num_scenes=1", "env.scene.grid=[1,1]"])
    env = NavEnv(cfg.env)
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    n = env.num_envs
    jax.eval_shape(env.step, state, jnp.zeros((n,), jnp.int32))
    with pytest.raises(AssertionError, match=rf"\[Chex\].*has shape \({n + 1},\) but expected \({n}\)"):
        jax.eval_shape(env.step, state, jnp.zeros((n + 1,), jnp.int32))
    with pytest.raises(AssertionError, match=r"\[Chex\].*type"):
        jax.eval_shape(env.step, state, jnp.zeros((n,), jnp.float32))
