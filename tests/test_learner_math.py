"""The learning maths of A2CAT-VN against independent computations.

- `losses`: bootstrapped returns, actor/critic/entropy losses (and which gradients
  they carry), pixel-control loss and the downsizing helpers against numpy loops
  written from their equations; the pixel-control loss also against
  `rlax.pixel_control_loss` on sequences without episode ends.
- `replay`: ring-buffer writes, sampling of whole sequences only from filled slots, and
  reward-prediction windows (inside one episode, balanced between zero and non-zero
  final reward, exactly the valid windows) against a numpy enumeration, with markers
  in the stored frames identifying every sampled position.
- `networks.Conv1`: the space-to-depth and plain paths against each other and against a
  numpy convolution.
- `update` / `acting`: the memory core is cleared exactly at episode starts (LSTM and
  frame stack), one update has finite metrics and gradients, and zero-weight replay
  losses remove the replay buffer and their terms.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import rlax

from a2catvn_jax.agent import acting, losses, networks
from a2catvn_jax.agent import replay as replay_lib
from a2catvn_jax.agent import update as update_lib
from a2catvn_jax.agent.types import Inputs
from a2catvn_jax.config import load_config
from a2catvn_jax.env import make_env
from a2catvn_jax.env.scenes.spec import NUM_CLASSES
from a2catvn_jax.env.scenes.spec import SEGMENTATION_COLORS
from tiny import TINY_SYNTHETIC

TINY = TINY_SYNTHETIC
NO_REPLAY = ["train.loss_weights.pixel_control=0", "train.loss_weights.reward_prediction=0",
             "train.loss_weights.off_policy_critic=0"]


def _gray(rgb):
    return rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114]) / 255.0


def _finite(tree):
    return all(bool(np.all(np.isfinite(np.asarray(x)))) for x in jax.tree_util.tree_leaves(tree))


# -- losses ---------------------------------------------------------------------------------


def test_bootstrapped_returns():
    rng = np.random.default_rng(0)
    T, B, gamma = 7, 5, 0.95
    rewards = rng.normal(size=(T, B)).astype(np.float32)
    dones = rng.random((T, B)) < 0.3
    dones[2, 0] = dones[T - 1, 1] = True
    bootstrap = rng.normal(size=B).astype(np.float32)
    expected = np.zeros((T, B))
    for b in range(B):
        g = float(bootstrap[b])
        for t in reversed(range(T)):
            g = rewards[t, b] + gamma * (1.0 - dones[t, b]) * g
            expected[t, b] = g
    got = losses.bootstrapped_returns(jnp.asarray(rewards), jnp.asarray(dones), jnp.asarray(bootstrap), gamma)
    np.testing.assert_allclose(np.asarray(got), expected, atol=1e-5, rtol=1e-5)


def test_actor_critic_losses_and_gradients():
    rng = np.random.default_rng(1)
    T, B, A = 5, 3, 6
    logits = rng.normal(size=(T, B, A)).astype(np.float32)
    values = rng.normal(size=(T, B)).astype(np.float32)
    returns = rng.normal(size=(T, B)).astype(np.float32)
    actions = rng.integers(0, A, size=(T, B)).astype(np.int32)

    lg = logits.astype(np.float64)
    log_p = lg - lg.max(-1, keepdims=True)
    log_p -= np.log(np.exp(log_p).sum(-1, keepdims=True))
    p = np.exp(log_p)
    adv = returns.astype(np.float64) - values
    log_p_a = np.take_along_axis(log_p, actions[..., None], -1)[..., 0]
    expected = (np.mean(-log_p_a * adv), np.mean(0.5 * adv**2), np.mean((p * log_p).sum(-1)))

    args = tuple(map(jnp.asarray, (logits, values, actions, returns)))
    got = losses.actor_critic_losses(*args)
    np.testing.assert_allclose(np.array(got, np.float64), expected, atol=1e-5, rtol=1e-5)

    term = lambda i, argnum: jax.grad(lambda *a: losses.actor_critic_losses(*a)[i], argnum)(*args)  # noqa: E731
    assert np.all(np.asarray(term(0, 1)) == 0.0)
    n = T * B
    np.testing.assert_allclose(np.asarray(term(1, 1)), -adv / n, atol=1e-6)
    onehot = np.eye(A)[actions]
    np.testing.assert_allclose(np.asarray(term(0, 0)), -(onehot - p) * adv[..., None] / n, atol=1e-6)


def _numpy_returns(rewards, dones, bootstrap, gamma, truncated=None, values=None):
    """Returns by the backward recursion, written from the equations of `bootstrapped_returns`."""
    T, B = rewards.shape
    out = np.zeros((T, B))
    for b in range(B):
        g = float(bootstrap[b])
        for t in reversed(range(T)):
            if truncated is not None and truncated[t, b]:
                g = float(values[t, b])  # a time-out: the critic's value of the state it was taken from
            else:
                g = rewards[t, b] + gamma * (1.0 - dones[t, b]) * g
            out[t, b] = g
    return out


def test_returns_bootstrap_from_the_critic_at_time_outs():
    rng = np.random.default_rng(11)
    T, B, gamma = 8, 4, 0.9
    rewards = rng.normal(size=(T, B)).astype(np.float32)
    terminated = rng.random((T, B)) < 0.15
    truncated = (rng.random((T, B)) < 0.2) & ~terminated
    truncated[3, 0], terminated[3, 0] = True, False
    dones = terminated | truncated
    values = rng.normal(size=(T, B)).astype(np.float32)
    bootstrap = rng.normal(size=B).astype(np.float32)
    args = tuple(map(jnp.asarray, (rewards, dones, bootstrap)))
    got = losses.bootstrapped_returns(*args, gamma, jnp.asarray(truncated), jnp.asarray(values))
    want = _numpy_returns(rewards, dones, bootstrap, gamma, truncated, values)
    np.testing.assert_allclose(np.asarray(got), want, atol=1e-5)
    # The step before a time-out bootstraps from the critic's value at the time-out's state.
    np.testing.assert_allclose(float(got[2, 0]), rewards[2, 0] + gamma * (1 - dones[2, 0]) * values[3, 0], atol=1e-5)
    # Without `truncated`, a time-out ends the sum like a terminal state (the paper's returns).
    paper = losses.bootstrapped_returns(*args, gamma)
    np.testing.assert_allclose(np.asarray(paper), _numpy_returns(rewards, dones, bootstrap, gamma), atol=1e-5)


@pytest.mark.parametrize("timeouts", [False, True])
def test_off_policy_critic_loss(timeouts):
    rng = np.random.default_rng(12)
    T, N, gamma = 6, 3, 0.95
    values = rng.normal(size=(T + 1, N)).astype(np.float32)
    rewards = rng.normal(size=(T, N)).astype(np.float32)
    truncated = rng.random((T, N)) < 0.2
    dones = truncated | (rng.random((T, N)) < 0.2)
    g = _numpy_returns(rewards, dones, values[-1], gamma, truncated if timeouts else None, values[:-1])
    want = np.mean(0.5 * (g - values[:-1]) ** 2)
    args = tuple(map(jnp.asarray, (values, rewards, dones)))
    trunc = jnp.asarray(truncated) if timeouts else None
    got = losses.off_policy_critic_loss(*args, gamma, trunc)
    np.testing.assert_allclose(float(got), want, rtol=1e-5)
    # The gradient reaches the values only through v(s_t) in (g_t - v(s_t)), the returns held constant.
    grad = jax.grad(lambda v: losses.off_policy_critic_loss(v, *args[1:], gamma, trunc))(args[0])
    np.testing.assert_allclose(np.asarray(grad[:-1]), -(g - values[:-1]) / (T * N), atol=1e-6)
    assert np.all(np.asarray(grad[-1]) == 0.0)


def test_reward_prediction_loss():
    rng = np.random.default_rng(13)
    logits = rng.normal(size=(7, 3)).astype(np.float32)
    reward = np.array([0.0, 1.0, -1.0, 0.5, 0.0, -0.2, 2.0], np.float32)
    classes = np.where(reward > 0, 1, np.where(reward < 0, 2, 0))
    np.testing.assert_array_equal(np.asarray(losses.reward_class(jnp.asarray(reward))), classes)
    log_p = logits - np.log(np.exp(logits).sum(-1, keepdims=True))
    want = -log_p[np.arange(7), classes].mean()
    np.testing.assert_allclose(float(losses.reward_prediction_loss(jnp.asarray(logits), jnp.asarray(reward))), want,
                               rtol=1e-5)


def test_sigmoid_reward_prediction_loss_and_its_gradient():
    """The per-class sigmoid binary cross-entropy, mean over windows and the 3 outputs, by
    hand; its gradient (s(z) - y) / 3N against the softmax one (softmax(z) - y) / N."""
    rng = np.random.default_rng(15)
    N = 9
    logits = rng.normal(scale=2.0, size=(N, 3)).astype(np.float32)
    reward = rng.choice([0.0, 1.0, -1.0], size=N).astype(np.float32)
    y = np.eye(3)[np.where(reward > 0, 1, np.where(reward < 0, 2, 0))]
    z = logits.astype(np.float64)
    s = 1.0 / (1.0 + np.exp(-z))
    want = -np.mean(y * np.log(s) + (1 - y) * np.log(1 - s))
    args = jnp.asarray(logits), jnp.asarray(reward)
    np.testing.assert_allclose(float(losses.reward_prediction_loss(*args, "sigmoid")), want, rtol=1e-5)
    # Zero rewards are class 0, positive class 1, negative class 2 (the same one-hot as the softmax loss).
    assert float(losses.reward_prediction_loss(jnp.asarray([[9.0, -9.0, -9.0]]), jnp.zeros(1), "sigmoid")) < 1e-3
    grad = lambda kind: np.asarray(jax.grad(lambda lg: losses.reward_prediction_loss(lg, args[1], kind))(args[0]))  # noqa: E731
    np.testing.assert_allclose(grad("sigmoid"), (s - y) / (3 * N), atol=1e-6)
    p_soft = np.exp(z) / np.exp(z).sum(-1, keepdims=True)
    np.testing.assert_allclose(grad("softmax"), (p_soft - y) / N, atol=1e-6)
    with pytest.raises(ValueError, match="hinge"):
        losses.reward_prediction_loss(*args, "hinge")


def test_vision_targets_and_losses():
    rng = np.random.default_rng(14)
    depth = rng.uniform(0.1, 9.0, size=(2, 8, 8)).astype(np.float32)
    want = depth.reshape(2, 2, 4, 2, 4).mean(axis=(2, 4)) * losses.DEPTH_SCALE
    np.testing.assert_allclose(np.asarray(losses.depth_targets(jnp.asarray(depth), 4)), want, rtol=1e-6)
    pred, target = rng.normal(size=(2, 2, 2, 3)), rng.uniform(size=(2, 2, 2, 3))
    np.testing.assert_allclose(float(losses.segmentation_loss(jnp.asarray(pred), jnp.asarray(target))),
                               np.mean((pred - target) ** 2), rtol=1e-5)
    logits, labels = rng.normal(size=(2, 2, 2, 5)), rng.integers(0, 5, size=(2, 2, 2))
    log_p = logits - np.log(np.exp(logits).sum(-1, keepdims=True))
    want = -np.take_along_axis(log_p, labels[..., None], -1).mean()
    np.testing.assert_allclose(float(losses.segmentation_loss(jnp.asarray(logits), jnp.asarray(labels))), want,
                               rtol=1e-5)


def _pc_inputs(seed, T, size, G, A):
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, size=(T + 1, size, size, 3), dtype=np.uint8)
    actions = rng.integers(0, A, size=T).astype(np.int32)
    q = rng.normal(size=(T + 1, G, G, A)).astype(np.float32)
    return rgb, actions, q


def test_pixel_control_loss_matches_rlax_without_dones():
    T, A, gamma, cell = 6, 5, 0.9, 4
    rgb, actions, q = _pc_inputs(2, T, 16, 4, A)
    gray = losses.grayscale(jnp.asarray(rgb))[..., None]
    reference = rlax.pixel_control_loss(gray, jnp.asarray(actions), jnp.asarray(q), gamma, cell)
    assert reference.shape == (T, 4, 4)
    got = losses.pixel_control_loss(jnp.asarray(rgb), jnp.asarray(actions), jnp.zeros(T, bool), jnp.asarray(q), gamma, cell)
    np.testing.assert_allclose(float(got), float(jnp.mean(reference)), rtol=1e-5)


def _numpy_pixel_change(rgb, kind):
    """|x_{t+1} - x_t| per pixel [T, H, W] of the luminance, or of R, G, B / 255 averaged over the channels."""
    if kind == "luminance":
        gray = _gray(rgb)
        return np.abs(gray[1:] - gray[:-1])
    x = rgb.astype(np.float64) / 255.0
    return np.abs(x[1:] - x[:-1]).mean(-1)


@pytest.mark.parametrize("kind", ["luminance", "rgb"])
def test_pixel_control_rewards(kind):
    """Per 4x4 cell, the mean absolute change of the luminance or of the three channels,
    by loops; an 18x18 image is cropped to 16x16 at the bottom and right."""
    rng = np.random.default_rng(16)
    T, size, cell = 3, 18, 4
    rgb = rng.integers(0, 256, size=(T + 1, size, size, 3), dtype=np.uint8)
    want = np.zeros((T, 4, 4))
    for t in range(T):
        for i in range(4):
            for j in range(4):
                block = rgb[t : t + 2, i * cell : (i + 1) * cell, j * cell : (j + 1) * cell].astype(np.float64)
                if kind == "luminance":
                    block = block @ np.array([0.299, 0.587, 0.114])
                want[t, i, j] = np.mean(np.abs(block[1] - block[0])) / 255.0
    got = losses.pixel_control_rewards(jnp.asarray(rgb), cell, kind)
    np.testing.assert_allclose(np.asarray(got), want, atol=1e-6)
    # A change of one channel only: the luminance weighs it by its coefficient, rgb by 1/3.
    still = np.zeros((2, 4, 4, 3), np.uint8)
    still[1, ..., 2] = 255
    one = float(losses.pixel_control_rewards(jnp.asarray(still), 4, kind)[0, 0, 0])
    np.testing.assert_allclose(one, 0.114 if kind == "luminance" else 1 / 3, rtol=1e-5)
    with pytest.raises(ValueError, match="depth"):
        losses.pixel_control_rewards(jnp.asarray(rgb), cell, "depth")


@pytest.mark.parametrize("kind", ["luminance", "rgb"])
def test_pixel_control_loss_with_dones_matches_numpy_q_lambda(kind):
    T, A, gamma, cell, size = 7, 4, 0.9, 4, 18  # 18x18 is cropped to 16x16: a 4x4 grid
    G = size // cell
    rgb, actions, q = _pc_inputs(3, T, size, G, A)
    dones = np.zeros(T, bool)
    dones[[2, 5]] = True

    diff = _numpy_pixel_change(rgb[:, : G * cell, : G * cell], kind)
    r = np.zeros((T, G, G))
    for t in range(T):
        for i in range(G):
            for j in range(G):
                r[t, i, j] = diff[t, i * cell : (i + 1) * cell, j * cell : (j + 1) * cell].mean() * (1 - dones[t])
    sq = []
    for i in range(G):
        for j in range(G):
            g = q[T, i, j].astype(np.float64).max()
            for t in reversed(range(T)):
                g = r[t, i, j] + gamma * (1 - dones[t]) * g
                sq.append(0.5 * (g - q[t, i, j, actions[t]]) ** 2)
    expected = np.mean(sq)

    got = losses.pixel_control_loss(jnp.asarray(rgb), jnp.asarray(actions), jnp.asarray(dones), jnp.asarray(q), gamma, cell,
                                    kind)
    np.testing.assert_allclose(float(got), expected, rtol=1e-5)


@pytest.mark.parametrize("shape,factor", [((2, 18, 18, 3), 4), ((2, 19, 17), 4), ((1, 17, 17, 2), 3)])
def test_downsize_mean_and_pick(shape, factor):
    rng = np.random.default_rng(4)
    x = rng.normal(size=shape).astype(np.float32)
    ids = rng.integers(0, 25, size=shape[:3]).astype(np.int32)
    hh, ww = shape[1] // factor, shape[2] // factor
    mean = np.zeros((shape[0], hh, ww) + shape[3:])
    pick = np.zeros((shape[0], hh, ww), np.int32)
    c = factor // 2
    for i in range(hh):
        for j in range(ww):
            mean[:, i, j] = x[:, i * factor : (i + 1) * factor, j * factor : (j + 1) * factor].mean(axis=(1, 2))
            pick[:, i, j] = ids[:, i * factor + c, j * factor + c]
    np.testing.assert_allclose(np.asarray(losses.downsize_mean(jnp.asarray(x), factor)), mean, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(losses.downsize_pick(jnp.asarray(ids), factor)), pick)


# -- replay ---------------------------------------------------------------------------------


def test_replay_add_wraps_around():
    L, B, slots = 3, 2, 3
    buf = replay_lib.init({"x": jnp.zeros((L, B), jnp.float32)}, jnp.zeros((B, 2)), slots)
    for k in range(slots + 1):
        if k == 2:
            np.testing.assert_array_equal(np.asarray(replay_lib.filled(buf)), [True, True, False])
        buf = replay_lib.add(buf, {"x": jnp.full((L, B), k + 1.0)}, jnp.full((B, 2), k + 1.0))
    assert int(buf.count) == slots + 1
    np.testing.assert_array_equal(np.asarray(buf.data["x"])[:, 0, 0], [4, 2, 3])
    np.testing.assert_array_equal(np.asarray(buf.carry)[:, 0, 0], [4, 2, 3])
    assert np.all(np.asarray(replay_lib.filled(buf)))


def test_sample_sequences_only_from_filled_slots():
    L, B, slots, n = 4, 3, 5, 500
    buf = replay_lib.init({"x": jnp.zeros((L, B), jnp.int32)}, jnp.zeros((B, 2), jnp.int32), slots)
    for k in range(2):
        value = 10 * (k + 1) + jnp.arange(B, dtype=jnp.int32)
        buf = replay_lib.add(buf, {"x": jnp.broadcast_to(value, (L, B))}, jnp.broadcast_to(value[:, None], (B, 2)))
    seqs, carry = replay_lib.sample_sequences(buf, jax.random.PRNGKey(0), n)
    x, carry = np.asarray(seqs["x"]), np.asarray(carry)
    assert x.shape == (L, n) and carry.shape == (n, 2)
    assert np.all(x == x[:1])
    assert np.all(carry == x[0][:, None])
    assert set(x[0].tolist()) == {10, 11, 12, 20, 21, 22}


def test_replay_keeps_a_rotating_block_of_environments():
    """With fewer kept environments than B, rollout k keeps environments kE .. kE+E-1
    (mod B) with their core state: every environment once per B / E rollouts."""
    L, B, E, slots = 2, 6, 4, 3
    buf = replay_lib.init({"x": jnp.zeros((L, B), jnp.int32)}, jnp.zeros((B, 2), jnp.int32), slots, envs=E)
    assert buf.data["x"].shape == (slots, L, E) and buf.carry.shape == (slots, E, 2)
    for k in range(4):
        value = 100 * (k + 1) + jnp.arange(B, dtype=jnp.int32)  # rollout k, environment b -> 100(k+1) + b
        buf = replay_lib.add(buf, {"x": jnp.broadcast_to(value, (L, B))}, jnp.broadcast_to(value[:, None], (B, 2)))
    x = np.asarray(buf.data["x"])
    assert np.all(x == x[:, :1])
    # Slots after 4 rollouts: slot 0 holds rollout 3, slots 1 and 2 rollouts 1 and 2.
    expect = {0: [400 + (12 + i) % B for i in range(E)], 1: [200 + (4 + i) % B for i in range(E)],
              2: [300 + (8 + i) % B for i in range(E)]}
    for slot, want in expect.items():
        np.testing.assert_array_equal(x[slot, 0], want)
        np.testing.assert_array_equal(np.asarray(buf.carry)[slot, :, 0], want)
    seqs, carry = replay_lib.sample_sequences(buf, jax.random.PRNGKey(1), 300)
    np.testing.assert_array_equal(np.asarray(carry)[:, 0], np.asarray(seqs["x"])[0])
    # As many kept environments as B (or more): the whole rollout, as without a limit.
    full = replay_lib.init({"x": jnp.zeros((L, B), jnp.int32)}, jnp.zeros((B, 2), jnp.int32), slots, envs=64)
    assert full.data["x"].shape == (slots, L, B)
    with pytest.raises(ValueError, match="at least one environment"):
        replay_lib.init({"x": jnp.zeros((L, B))}, jnp.zeros((B, 2)), slots, envs=0)


def _window_buffer(rewards_nonzero: bool, seed: int = 5):
    """4 slots, 3 filled; markers encode (rollout, step, env) in `target` and `rgb`."""
    L, B, slots, filled = 9, 3, 4, 3
    rng = np.random.default_rng(seed)
    example = {
        "rgb": jnp.zeros((L, B, 2, 2, 3), jnp.uint8),
        "target": jnp.zeros((L, B), jnp.int32),
        "reset": jnp.zeros((L, B), bool),
        "reward": jnp.zeros((L - 1, B), jnp.float32),
    }
    buf = replay_lib.init(example, jnp.zeros((B, 1)), slots)
    stored = []
    ll, bb = np.meshgrid(np.arange(L), np.arange(B), indexing="ij")
    for k in range(filled):
        reset = rng.random((L, B)) < 0.25
        reward = np.where(rng.random((L - 1, B)) < 0.15, rng.choice([-1.0, 0.5, 1.0], (L - 1, B)), 0.0)
        if not rewards_nonzero:
            reward[:] = 0.0
        rgb = np.broadcast_to(np.stack([np.full_like(ll, k + 1), ll, bb], -1)[:, :, None, None], (L, B, 2, 2, 3))
        rollout = {"rgb": rgb.astype(np.uint8), "target": 1 + 1000 * k + 10 * ll + bb, "reset": reset,
                   "reward": reward.astype(np.float32)}
        stored.append(rollout)
        buf = replay_lib.add(buf, jax.tree_util.tree_map(jnp.asarray, rollout), jnp.zeros((B, 1)))
    return buf, stored


@pytest.mark.parametrize("rewards_nonzero,frames,zero_fraction", [
    (True, 3, 0.5), (False, 3, 0.5), (True, 3, 1 / 3), (True, 4, 1 / 3), (True, 3, 0.0), (True, 4, 1.0), (False, 4, 0.0)])
def test_sample_reward_windows(rewards_nonzero, frames, zero_fraction):
    """Exactly the valid windows, and the share of those ending with zero reward measured
    over 4000 draws: `zero_fraction` when the buffer holds both kinds (one standard error
    is at most 0.008 here), otherwise all of the kind it holds."""
    n = 4000
    buf, stored = _window_buffer(rewards_nonzero)
    L, B = stored[0]["reset"].shape
    valid = {(k, t, b) for k, r in enumerate(stored) for t in range(frames - 1, L - 1) for b in range(B)
             if not r["reset"][t - frames + 2 : t + 1, b].any()}
    assert any(stored[k]["reward"][t, b] != 0 for k, t, b in valid) == rewards_nonzero

    win, reward = replay_lib.sample_reward_windows(buf, jax.random.PRNGKey(1), n, frames, buf.data["reward"],
                                                   buf.data["reset"], zero_fraction)
    target, rgb, reward = np.asarray(win["target"]), np.asarray(win["rgb"]), np.asarray(reward)
    assert target.shape == (n, frames) and rgb.shape == (n, frames, 2, 2, 3) and reward.shape == (n,)
    assert np.all(target > 0), "window from an unfilled slot"
    k, t, b = (target - 1) // 1000, (target - 1) % 1000 // 10, (target - 1) % 10
    np.testing.assert_array_equal(rgb[..., 0, 0, :], np.stack([k + 1, t, b], -1))
    assert np.all(k == k[:, :1]) and np.all(b == b[:, :1])
    np.testing.assert_array_equal(t, t[:, -1:] + np.arange(1 - frames, 1))
    last = list(zip(k[:, -1], t[:, -1], b[:, -1]))
    is_zero = {w: stored[w[0]]["reward"][w[1], w[2]] == 0 for w in valid}
    drawable = valid
    if len(set(is_zero.values())) == 2:  # both kinds stored: a kind of share 0 is never drawn
        drawable = {w for w, z in is_zero.items() if (zero_fraction > 0 if z else zero_fraction < 1)}
    assert set(last) == drawable
    np.testing.assert_array_equal(reward, [stored[kk]["reward"][tt, bb] for kk, tt, bb in last])
    if rewards_nonzero:
        assert abs(np.mean(reward == 0) - zero_fraction) < 0.03
    else:
        assert np.all(reward == 0)


def test_uniform_among_draws_each_true_entry_equally_often():
    """`replay.uniform_among`, the reward windows' sampler: only True entries, each about
    equally often (a chi-square test against uniform over 20,000 draws), and index 0 from
    a mask with none."""
    import scipy.stats

    mask = np.zeros((5, 3, 4), bool)
    mask.reshape(-1)[[0, 7, 8, 9, 23, 31, 40, 41, 58, 59]] = True
    idx = np.asarray(replay_lib.uniform_among(jax.random.PRNGKey(3), jnp.asarray(mask), 20000))
    assert set(idx.tolist()) == set(np.flatnonzero(mask).tolist())
    counts = np.bincount(idx, minlength=mask.size)[mask.reshape(-1)]
    assert scipy.stats.chisquare(counts).pvalue > 1e-3
    np.testing.assert_array_equal(replay_lib.uniform_among(jax.random.PRNGKey(3), jnp.zeros(6, bool), 4), 0)


# -- networks -------------------------------------------------------------------------------


@pytest.mark.parametrize("size", [16, 30, 64])
def test_conv1_space_to_depth_is_the_same_function(size):
    features = 8
    rng = np.random.default_rng(size)
    image = jnp.asarray(rng.integers(0, 256, size=(2, size, size, 3), dtype=np.uint8))
    params = networks.Conv1(features, True).init(jax.random.PRNGKey(0), image)
    params = {"params": dict(params["params"], bias=jnp.asarray(rng.normal(size=features).astype(np.float32)))}
    fast = np.asarray(networks.Conv1(features, True).apply(params, image))
    plain = np.asarray(networks.Conv1(features, False).apply(params, image))
    out = -(-size // 4)
    assert fast.shape == plain.shape == (2, out, out, features)
    assert np.max(np.abs(fast - plain)) < 1e-4
    if size <= 30:
        k = np.asarray(params["params"]["kernel"], np.float64)
        x = np.zeros((2, 4 + out * 4, 4 + out * 4, 3))
        x[:, 4 : 4 + size, 4 : 4 + size] = np.asarray(image) / 255.0
        ref = np.zeros((2, out, out, features))
        for i in range(out):
            for j in range(out):
                ref[:, i, j] = np.einsum("nuvc,uvcf->nf", x[:, 4 * i : 4 * i + 8, 4 * j : 4 * j + 8], k)
        ref += np.asarray(params["params"]["bias"])
        assert np.max(np.abs(plain - ref)) < 1e-4


# -- update ---------------------------------------------------------------------------------


@dataclasses.dataclass
class Setup:
    """One configuration's environment, network, update functions and initial state."""

    cfg: object
    env: object
    net: networks.Networks
    fns: update_lib.UpdateFns
    ts: object

    @property
    def target_feats(self):
        return self.net.target_stream(self.ts.params, self.env.target_images()["rgb"])

    def rollout(self, key):
        """(transition, frame truth) of one rollout from the initial state."""
        cfg, env, net = self.cfg, self.env, self.net

        @jax.jit
        def run(params, env_state, agent, key):
            feats = net.target_stream(params, env.target_images()["rgb"])
            traj, truth, *_ = acting.rollout(env, net, params, feats, env_state, agent, key, cfg.train.rollout_length,
                                             lambda obs: update_lib.frame_truth(update_lib.learner(cfg), obs.depth, obs.segmentation))
            return traj, truth

        return run(self.ts.params, self.ts.env_state, self.ts.agent, key)

    def loss(self, params, traj, truth, replay, key):
        targets = update_lib.targets_of(update_lib.learner(self.cfg), self.env)
        return update_lib.loss(update_lib.learner(self.cfg), self.net, targets, params, traj, truth, self.ts.agent.carry, replay, key)


FRAME_STACK = ["agent.memory=frame_stack", "agent.segmentation_loss=cross_entropy", "agent.space_to_depth=true"]


def _setup(overrides, env=None) -> Setup:
    cfg = load_config(None, TINY + overrides)
    env = env if env is not None else make_env(cfg.env)
    net = networks.make_networks(cfg, env.num_actions)
    fns = update_lib.make_update(env, net, cfg)
    return Setup(cfg, env, net, fns, fns.init(jax.random.PRNGKey(0)))


@pytest.fixture(scope="module")
def lstm():
    return _setup([])


@pytest.fixture(scope="module")
def frame_stack(lstm):
    """The non-default network settings together: frame stack, class-id segmentation, space-to-depth conv1."""
    return _setup(FRAME_STACK, env=lstm.env)


def _random_carry(net, n, seed):
    leaves, tree = jax.tree_util.tree_flatten(net.initial_carry(n))
    keys = jax.random.split(jax.random.PRNGKey(seed), len(leaves))
    return jax.tree_util.tree_unflatten(tree, [jax.random.normal(k, x.shape) for k, x in zip(keys, leaves)])


@pytest.mark.parametrize("memory", ["lstm", "frame_stack"])
def test_core_is_cleared_at_episode_starts(memory, request):
    setup = request.getfixturevalue(memory)
    net, ts = setup.net, setup.ts
    L, N, size, cut = 6, 3, setup.cfg.env.render.image_size, 3
    rng = np.random.default_rng(6)
    reset = np.zeros((L, N), bool)
    reset[cut, 0] = True  # env 0: an episode starts mid-sequence
    reset[0, 1] = True  # env 1: the sequence starts an episode; env 2: no episode start
    seq = Inputs(
        rgb=rng.integers(0, 256, (L, N, size, size, 3), dtype=np.uint8),
        target=rng.integers(0, setup.env.num_targets, (L, N)).astype(np.int32),
        prev_action=rng.integers(0, setup.env.num_actions, (L, N)).astype(np.int32),
        prev_reward=rng.normal(size=(L, N)).astype(np.float32),
        reset=reset,
    )
    seq = jax.tree_util.tree_map(jnp.asarray, seq)
    unroll = jax.jit(functools.partial(acting.unroll, net))
    feats = setup.target_feats
    core = lambda s, c: np.asarray(unroll(ts.params, feats, s, c)[1])  # noqa: E731
    a = core(seq, _random_carry(net, N, 1))
    b = core(seq, _random_carry(net, N, 2))
    zero = net.initial_carry(N)
    from_zero = core(seq, zero)
    tail = core(jax.tree_util.tree_map(lambda x: jnp.roll(x, -cut, axis=0), seq), zero)[: L - cut]

    np.testing.assert_allclose(a[cut:, 0], tail[:, 0], atol=1e-5)
    np.testing.assert_allclose(b[cut:, 0], tail[:, 0], atol=1e-5)
    assert np.max(np.abs(a[:cut, 0] - b[:cut, 0])) > 1e-3
    np.testing.assert_allclose(a[:, 1], from_zero[:, 1], atol=1e-5)
    np.testing.assert_allclose(b[:, 1], from_zero[:, 1], atol=1e-5)
    assert np.max(np.abs(a[0, 2] - b[0, 2])) > 1e-3


def test_loss_gradients_are_finite(lstm):
    ts = lstm.ts
    key = jax.random.PRNGKey(3)
    traj, truth = lstm.rollout(key)
    replay = replay_lib.add(ts.replay, traj, ts.agent.carry)
    grads, terms = jax.jit(jax.grad(lstm.loss, has_aux=True))(ts.params, traj, truth, replay, key)
    assert {"pixel_control", "reward_prediction", "off_policy_critic"} <= set(terms)
    assert _finite(grads) and _finite(terms)
    assert sum(float(jnp.sum(jnp.abs(g))) for g in jax.tree_util.tree_leaves(grads)) > 0


def test_update_metrics_are_finite(lstm):
    _, metrics = lstm.fns.update(jax.tree_util.tree_map(jnp.copy, lstm.ts))
    assert {"loss/pixel_control", "loss/reward_prediction", "loss/off_policy_critic", "loss/total"} <= set(metrics)
    assert _finite(metrics)


def test_zero_weights_remove_replay_losses(lstm):
    cfg = load_config(None, TINY + NO_REPLAY)
    assert not update_lib.uses_replay(cfg)
    fns = update_lib.make_update(lstm.env, lstm.net, cfg)
    ts = jax.eval_shape(fns.init, jax.random.PRNGKey(0))
    assert ts.replay is None
    _, metrics = jax.eval_shape(fns.update, ts)
    terms = {k[len("loss/"):] for k in metrics if k.startswith("loss/")}
    assert terms == {"actor", "critic", "entropy", "depth", "segmentation", "target_segmentation", "total"}


def test_replay_envs_bounds_the_buffer_and_the_update_runs(lstm):
    """`train.replay_envs` below B: the buffer keeps that many environments per rollout
    and the update trains from it (each replay term finite)."""
    cfg = load_config(None, TINY + ["train.replay_envs=3"])
    fns = update_lib.make_update(lstm.env, lstm.net, cfg)
    ts = jax.eval_shape(fns.init, jax.random.PRNGKey(0))
    B, slots = lstm.env.num_envs, cfg.train.replay_size // cfg.train.rollout_length
    assert ts.replay.data.rgb.shape[:3] == (slots, cfg.train.rollout_length + 1, 3) and B == 4
    assert lstm.ts.replay.data.rgb.shape[2] == B  # the default keeps all of a small batch
    ts, metrics = jax.jit(fns.update)(fns.init(jax.random.PRNGKey(0)))
    assert int(ts.replay.count) == 1
    assert {"loss/pixel_control", "loss/reward_prediction", "loss/off_policy_critic"} <= set(metrics)
    assert _finite(metrics)


AUTHORS_REPLAY = ["train.reward_prediction_loss=sigmoid", "train.reward_prediction_zero_fraction=0.3333",
                  "train.reward_prediction_target=next_frame", "train.pixel_control_reward=rgb"]


@pytest.mark.parametrize("overrides", [[], AUTHORS_REPLAY], ids=["default", "authors"])
def test_replay_term_settings_reach_the_losses(lstm, overrides):
    """Pixel control and reward prediction of `update.replay_terms`, recomputed from the
    sampling functions and the loss functions with the configured settings: reward
    windows of 3 frames predict the reward after the last one, or (next_frame) windows of
    4 frames whose first 3 the head sees predict the reward after the 4th."""
    cfg = load_config(None, TINY + ["train.loss_weights.off_policy_critic=0"] + overrides)
    tc, net, params = cfg.train, lstm.net, lstm.ts.params
    replay = lstm.ts.replay
    for seed in range(3):
        traj, _ = lstm.rollout(jax.random.PRNGKey(10 + seed))
        replay = replay_lib.add(replay, traj, lstm.ts.agent.carry)
    feats, key = lstm.target_feats, jax.random.PRNGKey(7)
    terms = jax.jit(functools.partial(update_lib.replay_terms, update_lib.learner(cfg), net))(params, feats, replay, key)

    k_seq, k_rp = jax.random.split(key)
    frames = 4 if overrides else 3
    win, reward = replay_lib.sample_reward_windows(replay, k_rp, tc.replay_batch, frames, replay.data.reward,
                                                   replay.data.reset, 0.3333 if overrides else 0.5)
    n, rp = tc.replay_batch, networks.RP_FRAMES
    rgb, target = win.rgb[:, :rp].reshape((n * rp,) + win.rgb.shape[2:]), win.target[:, :rp].reshape(-1)
    conv4, _ = net.encode(params, rgb, feats[target])
    logits = net.reward_prediction(params, conv4.reshape((n, rp) + conv4.shape[1:]))
    kind = "sigmoid" if overrides else "softmax"
    np.testing.assert_allclose(float(terms["reward_prediction"]), float(losses.reward_prediction_loss(logits, reward, kind)),
                               rtol=1e-4)

    seq, carry0 = replay_lib.sample_sequences(replay, k_seq, n)
    _, out = acting.unroll(net, params, feats, seq.inputs, carry0)
    q = networks.apply_flat(lambda x: net.pixel_control(params, x), out)
    pc = [losses.pixel_control_loss(seq.rgb[:, i], seq.action[:, i], seq.done[:, i], q[:, i], tc.pixel_control_gamma,
                                    tc.pixel_control_cell, "rgb" if overrides else "luminance") for i in range(n)]
    np.testing.assert_allclose(float(terms["pixel_control"]), float(np.mean(pc)), rtol=1e-4)


def test_aux_every_puts_the_vision_losses_on_every_kth_frame(lstm):
    """`train.aux_every` 3: the depth and both segmentation losses of `update.loss`
    are those of the heads on rollout frames 0, 3, 6, ... alone (recomputed here from
    the network and the loss functions), and differ from the all-frames losses."""
    cfg = load_config(None, TINY + ["train.aux_every=3"])
    traj, truth = lstm.rollout(jax.random.PRNGKey(12))
    targets = update_lib.targets_of(update_lib.learner(cfg), lstm.env)
    params, net = lstm.ts.params, lstm.net
    _, terms = jax.jit(functools.partial(update_lib.loss, update_lib.learner(cfg), net, targets))(
        params, traj, truth, lstm.ts.agent.carry, None, jax.random.PRNGKey(0))
    _, every = jax.jit(lstm.loss)(params, traj, truth, None, jax.random.PRNGKey(0))
    feats = net.target_stream(params, targets.rgb)
    conv4, _ = acting.unroll(net, params, feats, traj.inputs, lstm.ts.agent.carry)
    T1 = traj.inputs.rgb.shape[0]
    assert T1 > 3
    pick = np.arange(0, T1, 3)
    pred = networks.apply_flat(lambda x: net.vn_heads(params, x, ("depth", "segmentation", "target_segmentation")),
                               conv4[pick], 2)
    want = {
        "depth": losses.mse(pred["depth"], truth.depth[pick]),
        "segmentation": losses.segmentation_loss(pred["segmentation"], truth.segmentation[pick]),
        "target_segmentation": losses.segmentation_loss(pred["target_segmentation"],
                                                        targets.segmentation[traj.target][pick]),
    }
    for name, value in want.items():
        np.testing.assert_allclose(float(terms[name]), float(value), rtol=1e-5, err_msg=name)
        assert abs(float(terms[name]) - float(every[name])) > 1e-7, name
    for name in ("actor", "critic", "entropy"):
        np.testing.assert_allclose(float(terms[name]), float(every[name]), rtol=1e-6)


@pytest.mark.parametrize("setup, overrides", [("lstm", []), ("lstm", ["train.aux_every=3"]),
                                             ("frame_stack", FRAME_STACK)])
def test_remat_vision_heads_gives_the_same_losses_and_gradients(request, setup, overrides):
    """`train.remat_vision_heads`: the heads run one rollout step at a time and again in
    the backward pass instead of keeping their activations; every loss term and the
    gradient of the total are those of the plain loss (also with `aux_every`, and with
    the frame stack and class-id segmentation), and the compiled gradient program holds
    less memory."""
    base = request.getfixturevalue(setup)
    plain_cfg = load_config(None, TINY + overrides)
    cfg = load_config(None, TINY + overrides + ["train.remat_vision_heads=true"])
    traj, truth = base.rollout(jax.random.PRNGKey(13))
    targets = update_lib.targets_of(update_lib.learner(cfg), base.env)
    params, carry = base.ts.params, base.ts.agent.carry

    def grad_of(c):
        loss = functools.partial(update_lib.loss, update_lib.learner(c), base.net, targets)
        return jax.jit(jax.grad(lambda p: loss(p, traj, truth, carry, None, jax.random.PRNGKey(0)), has_aux=True))

    plain, remat = grad_of(plain_cfg), grad_of(cfg)
    (g0, t0), (g1, t1) = plain(params), remat(params)
    assert set(t0) == set(t1) and {"depth", "segmentation", "target_segmentation"} <= set(t1)
    for name in t0:
        np.testing.assert_allclose(float(t1[name]), float(t0[name]), rtol=1e-6, err_msg=name)
    for a, b in zip(jax.tree_util.tree_leaves(g0), jax.tree_util.tree_leaves(g1)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-4, atol=1e-7)
    memory = [f.lower(params).compile().memory_analysis().temp_size_in_bytes for f in (plain, remat)]
    assert memory[1] < memory[0], memory


def test_segmentation_targets_in_both_encodings(lstm, frame_stack):
    seg = np.random.default_rng(0).integers(0, NUM_CLASSES, (2, 16, 16))
    factor = lstm.cfg.train.aux_downsize
    colours = losses.segmentation_targets(jnp.asarray(seg), factor, update_lib.segmentation_colors(lstm.cfg))
    ids = losses.segmentation_targets(jnp.asarray(seg), factor, update_lib.segmentation_colors(frame_stack.cfg))
    want = (SEGMENTATION_COLORS[seg] / 255.0).reshape(2, 4, factor, 4, factor, 3).mean(axis=(2, 4))
    np.testing.assert_allclose(np.asarray(colours), want, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(ids), seg[:, factor // 2 :: factor, factor // 2 :: factor])


def test_cross_entropy_segmentation_update(frame_stack):
    setup = frame_stack
    ts, net = setup.ts, setup.net
    key = jax.random.PRNGKey(4)
    traj, truth = setup.rollout(key)
    _, terms = jax.jit(setup.loss)(ts.params, traj, truth, None, key)
    conv4, _ = jax.jit(functools.partial(acting.unroll, net))(ts.params, setup.target_feats, traj.inputs, ts.agent.carry)
    pred = net.vn_heads(ts.params, conv4.reshape((-1,) + conv4.shape[2:]))
    logits = np.asarray(pred["segmentation"], np.float64)
    assert logits.shape[-1] == NUM_CLASSES
    labels = np.asarray(truth.segmentation).reshape(logits.shape[:-1])
    log_p = logits - logits.max(-1, keepdims=True)
    log_p -= np.log(np.exp(log_p).sum(-1, keepdims=True))
    want = -np.take_along_axis(log_p, labels[..., None], -1).mean()
    np.testing.assert_allclose(float(terms["segmentation"]), want, rtol=1e-4)
    _, metrics = setup.fns.update(jax.tree_util.tree_map(jnp.copy, ts))
    assert _finite(metrics)


def test_curriculum_schedule_drives_the_environment(lstm):
    """tau rises linearly between the two frame counts, reaches the environment, and needs no recompile."""
    extra = ["train.curriculum=true", "train.curriculum_complexity=[0.2,0.8]", "train.curriculum_frames=[16,48]"]
    cfg = load_config(None, TINY + extra)
    fns = update_lib.make_update(lstm.env, lstm.net, cfg)
    per_update = update_lib.frames_per_update(cfg)  # 16 frames
    ts = fns.init(jax.random.PRNGKey(0))
    assert np.allclose(np.asarray(ts.env_state.info.complexity), 0.2)
    seen = []
    for _ in range(5):
        ts, metrics = fns.update(ts)
        seen.append(float(metrics["complexity"]))
        assert np.allclose(np.asarray(ts.env_state.info.complexity), seen[-1])
    frames = np.arange(5) * per_update
    want = 0.2 + 0.6 * np.clip((frames - 16) / 32, 0, 1)
    np.testing.assert_allclose(seen, want, atol=1e-6)
    assert fns.update._cache_size() == 1


def test_time_out_setting_reaches_the_losses(lstm):
    """With episodes cut every 2 steps, the rollout holds time-outs; bootstrapping at them
    (the default) and treating them as terminal (the paper) give different critic losses."""
    cfgs = {flag: load_config(None, TINY + ["env.max_episode_steps=2", "env.success_distance=0.1",
                                            f"train.timeout_bootstrap={flag}"]) for flag in ("true", "false")}
    env = make_env(cfgs["true"].env)
    setups = {flag: Setup(cfg, env, lstm.net, None, None) for flag, cfg in cfgs.items()}
    fns = update_lib.make_update(env, lstm.net, cfgs["true"])
    ts = fns.init(jax.random.PRNGKey(0))
    for s in setups.values():
        s.ts = ts
    key = jax.random.PRNGKey(5)
    traj, truth = setups["true"].rollout(key)
    assert np.asarray(traj.truncated).any()
    terms = {flag: jax.jit(s.loss)(ts.params, traj, truth, None, key)[1] for flag, s in setups.items()}
    assert float(terms["true"]["critic"]) != float(terms["false"]["critic"])
    assert float(terms["true"]["actor"]) != float(terms["false"]["actor"])
    assert _finite(terms)


def test_grad_norms_of_each_term_on_the_shared_layers(lstm):
    """The diagnostic's per-term norms are the norms of each weighted term's own gradient
    on conv1-conv4, computed here directly."""
    ts = lstm.ts
    norms = jax.device_get(update_lib.make_grad_norms(lstm.env, lstm.net, lstm.cfg)(ts))
    spec = update_lib.learner(lstm.cfg)
    targets = update_lib.targets_of(spec, lstm.env)
    batch = update_lib.collect(spec, lstm.env, lstm.net, targets, ts)
    w = lstm.cfg.train.loss_weights

    def shared_norm(name):
        term = lambda p: getattr(w, name) * update_lib.loss(spec, lstm.net, targets, p, *batch.loss_args)[1][name]  # noqa: E731
        g = jax.jit(jax.grad(term))(ts.params)["params"]
        return float(np.sqrt(sum(np.sum(np.square(np.asarray(x))) for k in networks.SHARED_LAYERS
                                 for x in jax.tree_util.tree_leaves(g[k]))))

    for name in ("actor", "reward_prediction"):
        np.testing.assert_allclose(norms[f"grad_norm/{name}"], shared_norm(name), rtol=1e-4)
    per_term = [v for k, v in norms.items() if k != "grad_norm/total_shared"]
    assert norms["grad_norm/total_shared"] <= sum(per_term) + 1e-6
