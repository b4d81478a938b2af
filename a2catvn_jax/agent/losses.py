"""Loss terms of A2CAT-VN, as pure functions of arrays (time-major: [T, B, ...]).

Each function computes one term from network outputs and data, with its equation in
the docstring; `update.py` composes them with the configured weights.

Returns follow the paper's eq. (1): every step of a rollout is bootstrapped from the
critic's value at the end of the rollout (a mixture of n-step returns), and the
bootstrap is cut where an episode ended. Pixel control is Peng's Q(1), i.e. n-step
Q-learning bootstrapped by max_a Q at the end of the sequence, on pseudo-rewards that
are the mean absolute change of the grayscale image (or of R, G and B) in each cell;
both come from rlax.

Every function checks the ranks and shapes of its inputs with chex when it is traced
(no cost at run time): a misshaped input fails there, naming the shapes, instead of
broadcasting into a wrong loss.

Every term is a mean over its elements (steps, sequences, cells, pixels), not the sum
over the rollout that the paper's equations write; the squared-error terms carry a
1/2 (critic, off-policy critic, pixel control), so that a weight w here equals a weight
w/2 on a plain mean squared error. docs/method.md compares these choices with the
paper and the authors' code.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import rlax

GRAY = np.array([0.299, 0.587, 0.114], np.float32)  # NumPy: importing the package starts no JAX backend


def bootstrapped_returns(rewards, dones, bootstrap, gamma: float, truncated=None, values=None):
    """g_t = r_{t+1} + gamma r_{t+2} + ... + gamma^n 1_c v(s_{t+n}), n = steps to the end.

    rewards, dones [T, B]; bootstrap [B] (value of the state after the last step).
    The sum and the bootstrap stop at an episode end (done).

    With `truncated` [T, B] (steps where an episode hit its time limit, a subset of
    `dones`) and `values` [T, B] (the critic's v(s_t), held constant by the caller), a
    time-out is not terminal: the return of the step it happened at is the critic's
    value of the state it was taken from, g_t = v(s_t), so that the steps before it
    bootstrap from that value (g_{t-1} = r_t + gamma v(s_t)) and the step itself, whose
    next state the auto-reset replaced, gives no learning signal (g_t - v(s_t) = 0).
    """
    chex.assert_rank([rewards, dones, bootstrap], [2, 2, 1])
    chex.assert_equal_shape([rewards, dones] + [x for x in (truncated, values) if x is not None])
    chex.assert_shape(bootstrap, rewards.shape[1:])
    discounts = gamma * (1.0 - dones.astype(jnp.float32))
    if truncated is not None:
        rewards = jnp.where(truncated, values, rewards)
    ends = jnp.broadcast_to(bootstrap, rewards.shape)
    return jax.vmap(rlax.discounted_returns, in_axes=1, out_axes=1)(rewards, discounts, ends)


def actor_critic_losses(logits, values, actions, returns):
    """(actor, critic, negative-entropy) losses, each a mean over [T, B].

    actor: -log pi(a|s) * (g - v) with the advantage held constant; critic:
    1/2 (g - v)^2; negative entropy: sum_a pi log pi.
    """
    chex.assert_rank([logits, values, actions, returns], [3, 2, 2, 2])
    chex.assert_equal_shape([values, actions, returns, logits[..., 0]])
    chex.assert_type(actions, int)
    log_pi = jax.nn.log_softmax(logits)
    log_pi_a = jnp.take_along_axis(log_pi, actions[..., None], -1)[..., 0]
    advantage = jax.lax.stop_gradient(returns - values)
    actor = -jnp.mean(log_pi_a * advantage)
    critic = jnp.mean(0.5 * jnp.square(returns - values))
    neg_entropy = jnp.mean(jnp.sum(jnp.exp(log_pi) * log_pi, -1))
    return actor, critic, neg_entropy


def off_policy_critic_loss(values, rewards, dones, gamma: float, truncated=None):
    """Critic loss on a replayed sequence, mean over [T, N] of 1/2 (g_t - v(s_t))^2.

    values [T+1, N] of the current critic on the sequence's T+1 states; rewards,
    dones [T, N]. g_t are `bootstrapped_returns` from the (constant) value of the last
    state, cut at episode ends; with `truncated` [T, N], time-outs bootstrap from the
    critic instead (see `bootstrapped_returns`).
    """
    chex.assert_rank([values, rewards, dones], 2)
    chex.assert_equal_shape([values[:-1], rewards, dones])
    held = jax.lax.stop_gradient(values)
    returns = bootstrapped_returns(rewards, dones, held[-1], gamma, truncated, None if truncated is None else held[:-1])
    return jnp.mean(0.5 * jnp.square(returns - values[:-1]))


def reward_class(reward):
    """Reward-prediction class of rewards [...]: 0 zero, 1 positive, 2 negative."""
    return jnp.where(reward > 0, 1, jnp.where(reward < 0, 2, 0)).astype(jnp.int32)


def reward_prediction_loss(logits, reward, kind: str = "softmax"):
    """Reward-prediction loss of logits [N, 3] for the rewards [N] that followed each
    window, with y the one-hot class of `reward_class`:

    - "softmax": the cross-entropy -log softmax(z)_y, mean over N;
    - "sigmoid": each output a separate binary classifier, the binary cross-entropy
      -[y_c log s(z_c) + (1 - y_c) log(1 - s(z_c))] with s the logistic sigmoid, mean
      over N and the 3 outputs. Its gradient with respect to z_c is (s(z_c) - y_c) / 3N,
      about a third of the softmax one's (softmax(z)_c - y_c) / N.
    """
    chex.assert_rank([logits, reward], [2, 1])
    chex.assert_equal_shape_prefix([logits, reward], 1)
    labels = reward_class(reward)
    if kind == "softmax":
        return cross_entropy(logits, labels)
    if kind == "sigmoid":
        y = jax.nn.one_hot(labels, logits.shape[-1], dtype=logits.dtype)
        return -jnp.mean(y * jax.nn.log_sigmoid(logits) + (1.0 - y) * jax.nn.log_sigmoid(-logits))
    raise ValueError(f"unknown reward-prediction loss {kind!r}")


def grayscale(rgb):
    """uint8 [..., 3] -> float32 [...] in [0, 1]."""
    return rgb.astype(jnp.float32) @ GRAY / 255.0


def pixel_control_rewards(rgb, cell: int, kind: str = "luminance"):
    """Pseudo-rewards [T, G, G] of a sequence of T+1 uint8 images [T+1, H, W, 3]: per
    cell x cell block (image cropped to a multiple of `cell` at the bottom and right),
    the mean absolute change of the luminance (`kind` "luminance"), or of R, G and B
    scaled to [0, 1] and averaged over the three channels ("rgb")."""
    if kind == "luminance":
        x = grayscale(rgb)[..., None]
    elif kind == "rgb":
        x = rgb.astype(jnp.float32) / 255.0
    else:
        raise ValueError(f"unknown pixel-control reward {kind!r}")
    g_h, g_w = x.shape[1] // cell, x.shape[2] // cell
    return rlax.pixel_control_rewards(x[:, : g_h * cell, : g_w * cell], cell)


def pixel_control_loss(rgb, actions, dones, q_values, gamma: float, cell: int, reward: str = "luminance"):
    """n-step Q-learning loss for pixel control on one sequence, mean over steps and cells
    of 1/2 (target - Q)^2.

    rgb [T+1, H, W, 3] uint8; actions, dones [T]; q_values [T+1, G, G, A]; `reward` the
    kind of `pixel_control_rewards`. A step that ended an episode has no pseudo-reward
    (its next frame belongs to a new episode) and no bootstrap beyond it.
    """
    chex.assert_rank([rgb, actions, dones, q_values], [4, 1, 1, 4])
    chex.assert_type(rgb, jnp.uint8)
    chex.assert_equal_shape([actions, dones])
    T = actions.shape[0]
    chex.assert_axis_dimension(rgb, 0, T + 1)
    chex.assert_axis_dimension(q_values, 0, T + 1)
    not_done = 1.0 - dones.astype(jnp.float32)
    rewards = pixel_control_rewards(rgb, cell, reward) * not_done[:, None, None]
    A = q_values.shape[-1]
    q_tm1 = q_values[:-1].reshape(T, -1, A)
    q_t = q_values[1:].reshape(T, -1, A)
    r_t = rewards.reshape(T, -1)
    cells = r_t.shape[1]
    a_tm1 = jnp.broadcast_to(actions[:, None], (T, cells))
    discount = jnp.broadcast_to((gamma * not_done)[:, None], (T, cells))
    q_lambda = jax.vmap(lambda q1, a, r, d, q2: rlax.q_lambda(q1, a, r, d, q2, lambda_=1.0), in_axes=1, out_axes=1)
    td = q_lambda(q_tm1, a_tm1, r_t, discount, q_t)
    return jnp.mean(0.5 * jnp.square(td))


def downsize_mean(x, factor: int):
    """Average over factor x factor blocks of [N, H, W, ...] (cropped to a multiple of factor)."""
    n, h, w = x.shape[:3]
    hh, ww = h // factor, w // factor
    x = x[:, : hh * factor, : ww * factor].astype(jnp.float32)
    return x.reshape((n, hh, factor, ww, factor) + x.shape[3:]).mean(axis=(2, 4))


def downsize_pick(x, factor: int):
    """The centre pixel of each factor x factor block of [N, H, W] (class ids)."""
    n, h, w = x.shape[:3]
    hh, ww = h // factor, w // factor
    c = factor // 2
    return x[:, c : hh * factor : factor, c : ww * factor : factor]


def mse(prediction, target):
    """mean (prediction - target)^2 over every element (shapes must be equal)."""
    chex.assert_equal_shape([prediction, target])
    return jnp.mean(jnp.square(prediction - target))


def cross_entropy(logits, labels):
    """Mean softmax cross-entropy of logits [..., C] against integer labels [...]."""
    chex.assert_equal_shape([logits[..., 0], labels])
    log_p = jax.nn.log_softmax(logits)
    return -jnp.mean(jnp.take_along_axis(log_p, labels[..., None].astype(jnp.int32), -1))


DEPTH_SCALE = 0.1  # depth targets are metres * DEPTH_SCALE


def depth_targets(depth, factor: int):
    """Depth ground truth of frames [N, H, W] (metres) at 1/factor resolution, scaled by DEPTH_SCALE."""
    return downsize_mean(depth, factor) * DEPTH_SCALE


def segmentation_targets(segmentation, factor: int, colors=None):
    """Segmentation ground truth of class ids [N, H, W] at 1/factor resolution: the block
    means of the class colours `colors` [C, 3] in [0, 1] (the paper's encoding, for an MSE
    loss), or with `colors` None the centre pixel's class id (for a cross-entropy loss)."""
    if colors is None:
        return downsize_pick(segmentation, factor).astype(jnp.int32)
    return downsize_mean(colors[segmentation], factor)


def segmentation_loss(prediction, target):
    """MSE of predicted colours [..., 3] against colour targets, or the softmax cross-entropy
    of class logits [..., C] against integer class targets [...]."""
    if jnp.issubdtype(target.dtype, jnp.integer):
        return cross_entropy(prediction, target)
    return mse(prediction, target)
