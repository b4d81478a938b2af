"""A functional replay buffer of whole rollouts.

The buffer keeps the last `slots` rollouts of E of the B environments: every leaf of a
rollout pytree (a `Transition`) `[L, B, ...]` is stored at `[slot, L, E, ...]`, with the
memory-core state the rollout started from (so replayed sequences are unrolled from the
state the agent really had). With E = B every environment's rollout is kept; with E < B
each rollout keeps a different block of E consecutive environments (rollout k keeps
environments kE, ..., kE + E - 1, modulo B), so over B / E rollouts every environment is
stored once and the memory is `slots * L * E` steps however large B grows, while the
age of what is replayed (the last `slots` rollouts) stays the same. Everything is a
fixed-shape pytree, so adding and sampling happen inside the jitted update.

Sampling:
- `sample_sequences`: n (rollout, environment) pairs, uniformly among the stored ones;
  each is a whole rollout sequence of one environment.
- `sample_reward_windows`: n windows of `frames` consecutive steps inside one episode,
  a share `zero_fraction` of them (in expectation; half by default) ending with zero
  reward and the rest with a non-zero reward, when the buffer holds both kinds
  (reward prediction).
"""

from __future__ import annotations

from typing import Any, Optional

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Replay:
    data: Any  # rollout pytree, leaves [slots, L, B, ...]
    carry: object  # core state pytree, leaves [slots, B, ...]
    count: jnp.ndarray  # rollouts written so far (int32)

    @property
    def slots(self) -> int:
        return jax.tree_util.tree_leaves(self.data)[0].shape[0]


def init(example, example_carry, slots: int, envs: Optional[int] = None) -> Replay:
    """An empty buffer for rollouts shaped like `example` (leaves [L, B, ...]) that keeps
    `envs` environments of each (default: all B)."""
    B = jax.tree_util.tree_leaves(example_carry)[0].shape[0]
    E = B if envs is None else min(envs, B)
    if E < 1:
        raise ValueError(f"the replay must keep at least one environment per rollout, got {envs}")
    zeros = lambda axis: lambda x: jnp.zeros(  # noqa: E731
        (slots,) + x.shape[:axis] + (E,) + x.shape[axis + 1:], x.dtype)
    return Replay(
        jax.tree_util.tree_map(zeros(1), example),
        jax.tree_util.tree_map(zeros(0), example_carry),
        jnp.zeros((), jnp.int32),
    )


def stored_envs(replay: Replay, num_envs: int):
    """[E] int32: the environments (of `num_envs`) whose rollout the next `add` keeps
    (all of them, in order, when E = num_envs)."""
    E = jax.tree_util.tree_leaves(replay.carry)[0].shape[1]
    return (replay.count * E + jnp.arange(E)) % num_envs


def add(replay: Replay, rollout, carry) -> Replay:
    """The buffer with `rollout` (leaves [L, B, ...], core state [B, ...]), or the block
    of its environments that `stored_envs` names, written over the oldest slot."""
    slot = replay.count % replay.slots
    B = jax.tree_util.tree_leaves(carry)[0].shape[0]
    E = jax.tree_util.tree_leaves(replay.carry)[0].shape[1]
    if E != B:
        envs = stored_envs(replay, B)
        rollout = jax.tree_util.tree_map(lambda x: jnp.take(x, envs, axis=1), rollout)
        carry = jax.tree_util.tree_map(lambda x: jnp.take(x, envs, axis=0), carry)
    put = lambda buf, x: jax.lax.dynamic_update_index_in_dim(buf, x.astype(buf.dtype), slot, 0)  # noqa: E731
    return Replay(
        jax.tree_util.tree_map(put, replay.data, rollout),
        jax.tree_util.tree_map(put, replay.carry, carry),
        replay.count + 1,
    )


def filled(replay: Replay):
    """[slots] bool: slots holding a rollout."""
    return jnp.arange(replay.slots) < replay.count


def sample_sequences(replay: Replay, key, n: int):
    """n whole sequences: (rollout pytree with leaves [L, n, ...], core state leaves [n, ...])."""
    B = jax.tree_util.tree_leaves(replay.carry)[0].shape[1]
    ks, kb = jax.random.split(key)
    logits = jnp.where(filled(replay), 0.0, -jnp.inf)
    slot = jax.random.categorical(ks, logits, shape=(n,))
    env = jax.random.randint(kb, (n,), 0, B)
    seqs = jax.tree_util.tree_map(lambda x: jnp.moveaxis(x[slot, :, env], 0, 1), replay.data)
    carry = jax.tree_util.tree_map(lambda c: c[slot, env], replay.carry)
    return seqs, carry


def uniform_among(key, mask, n: int):
    """[n] flat indices of `mask`, each drawn uniformly among its True entries (index 0
    when there are none). By the inverse of the count of True entries: O(N + n log N)
    for N entries, where drawing from a categorical costs n x N random numbers (at B 256
    with 5-step rollouts, N is 100k windows)."""
    counts = jnp.cumsum(mask.reshape(-1).astype(jnp.int32))
    k = jax.random.randint(key, (n,), 0, jnp.maximum(counts[-1], 1))
    return jnp.where(counts[-1] > 0, jnp.searchsorted(counts, k, side="right"), 0).astype(jnp.int32)


def sample_reward_windows(replay: Replay, key, n: int, frames: int, reward, reset, zero_fraction: float = 0.5):
    """n windows of `frames` consecutive steps of one environment inside one episode.

    reward [slots, L-1, B] are the stored rollouts' rewards and reset [slots, L, B] their
    episode starts. Returns (rollout pytree with leaves [n, frames, ...], reward [n] of
    the last step). The windows come from the first L-1 steps of stored rollouts (those
    with a recorded reward); a window may not cross an episode start (a `reset` after
    its first frame). Each window independently ends with zero reward with probability
    `zero_fraction` and with a non-zero one otherwise, drawn uniformly among the windows
    of its kind; when the buffer holds windows of only one kind, all come from it.
    """
    S, T, B = reward.shape
    t = jnp.arange(T)
    # Window ending at step t: frames t-frames+1 .. t; none of frames after the first may start an episode.
    starts = jnp.zeros((S, T, B), bool)
    for k in range(frames - 1):
        starts = starts | jnp.roll(reset[:, :T], k, axis=1)
    ok = (t[None, :, None] >= frames - 1) & ~starts & filled(replay)[:, None, None]
    nonzero = ok & (reward != 0)
    zero = ok & (reward == 0)
    k_kind, k_nz, k_z = jax.random.split(key, 3)
    want_nonzero = jax.random.bernoulli(k_kind, 1.0 - zero_fraction, (n,)) & jnp.any(nonzero)
    idx = jnp.where(want_nonzero, uniform_among(k_nz, nonzero, n), uniform_among(k_z, jnp.where(jnp.any(zero), zero, ok), n))
    slot, step, env = idx // (T * B), (idx // B) % T, idx % B
    window = step[:, None] + jnp.arange(1 - frames, 1)[None, :]  # [n, frames]
    out = jax.tree_util.tree_map(lambda x: x[slot[:, None], window, env[:, None]], replay.data)
    return out, reward[slot, step, env]
