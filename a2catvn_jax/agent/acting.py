"""Acting: the network inputs of a step, the policy, the memory core over sequences and
the rollout scan. Pure functions of the `Networks` and their parameters, shared by the
update, evaluation, pre-training and inspection."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from a2catvn_jax.agent.networks import Carry, Networks, Params, apply_flat
from a2catvn_jax.agent.types import AgentState, Inputs, Transition
from a2catvn_jax.env import Observation


def initial_agent(networks: Networks, batch: int) -> AgentState:
    """The agent state of `batch` environments before their first step."""
    return AgentState(networks.initial_carry(batch), jnp.zeros((batch,), jnp.int32), jnp.zeros((batch,), jnp.float32),
                      jnp.ones((batch,), bool))


def step_inputs(obs: Observation, agent: AgentState) -> Inputs:
    """The network inputs [B] of the current step: the observation, the target's index,
    and what the agent carries."""
    return Inputs(obs.rgb, obs.target_index, agent.prev_action, agent.prev_reward, agent.reset)


def policy(networks: Networks, params: Params, target_feats, carry: Carry, inputs: Inputs):
    """One step: (new core state, logits [N, A], value [N]). `target_feats` [K, ...] are
    the target stream's features of every distinct target image."""
    _, feats = networks.encode(params, inputs.rgb, target_feats[inputs.target])
    carry = networks.clear(carry, inputs.reset)
    carry, out = networks.core(params, carry, feats, inputs.prev_action, inputs.prev_reward)
    logits, value = networks.actor_critic(params, out)
    return carry, logits, value


def act(networks: Networks, params: Params, target_feats, agent: AgentState, obs: Observation, key,
        greedy: bool = False):
    """(core state after this step, action [B] int32, logits, value) of the policy, sampled
    or (greedy) its argmax."""
    carry, logits, value = policy(networks, params, target_feats, agent.carry, step_inputs(obs, agent))
    action = jnp.argmax(logits, -1) if greedy else jax.random.categorical(key, logits)
    return carry, action.astype(jnp.int32), logits, value


ACTION_RULES = ("sample", "greedy", "random")  # how `act_as` turns the network's output into actions


def act_as(policy: str, networks: Networks, params: Params, target_feats, agent: AgentState, obs: Observation, key):
    """(core state after this step, action [B] int32) of the policy sampled ("sample"), its
    argmax ("greedy"), or uniformly random actions ("random": the core still runs, so the
    agent state stays that of the network)."""
    core, action, logits, _ = act(networks, params, target_feats, agent, obs, key, policy == "greedy")
    if policy == "random":
        action = jax.random.randint(key, action.shape, 0, logits.shape[-1])
    return core, action


def observe(carry: Carry, action, env_state) -> AgentState:
    """Agent state after the environment answered `action` with `env_state`."""
    return AgentState(carry, action, env_state.reward, env_state.done)


def unroll(networks: Networks, params: Params, target_feats, inputs: Inputs, carry0: Carry):
    """The network over a sequence [L, N]: (conv4 maps [L, N, ...], core outputs [L, N, core]).
    The conv base runs on all L*N frames at once, the core step by step from `carry0`."""
    L, N = inputs.rgb.shape[:2]
    flat = lambda x: x.reshape((L * N,) + x.shape[2:])  # noqa: E731
    conv4, feats = networks.encode(params, flat(inputs.rgb), target_feats[flat(inputs.target)])
    feats = feats.reshape(L, N, -1)

    def body(carry, x):
        f, prev_action, prev_reward, reset = x
        carry = networks.clear(carry, reset)
        return networks.core(params, carry, f, prev_action, prev_reward)

    _, outs = jax.lax.scan(body, carry0, (feats, inputs.prev_action, inputs.prev_reward, inputs.reset))
    return conv4.reshape((L, N) + conv4.shape[1:]), outs


def actor_critic_sequence(networks: Networks, params: Params, core_out):
    """(logits [L, N, A], values [L, N]) of core outputs [L, N, core]."""
    return apply_flat(lambda x: networks.actor_critic(params, x), core_out)


EPISODE_STATS = ("episodes", "successes", "length_sum", "spl_sum", "return_sum")


def episode_stats(env_state) -> dict:
    """Sums over the environments of the episodes the last step ended (see `EPISODE_STATS`)."""
    m, done = env_state.metrics, env_state.done
    return {
        "episodes": done.sum(),
        "successes": (m["success"] & done).sum(),
        "length_sum": jnp.where(done, m["episode_length"], 0).sum(),
        "spl_sum": jnp.where(done, m["episode_spl"], 0.0).sum(),
        "return_sum": jnp.where(done, m["episode_return"], 0.0).sum(),
    }


def rollout(env, networks: Networks, params: Params, target_feats, env_state, agent: AgentState, key, steps: int,
            truth: Callable[[Observation], object], world=None):
    """`steps` steps of the sampled policy in all environments, in one `lax.scan`.

    `world` is the environment's world arrays (default: its own). Returns (transition
    [steps(+1), B], frame truth [steps+1, B] of `truth(obs)`, env state, agent state,
    episode stats summed over the steps)."""

    def step(carry, k):
        env_state, agent = carry
        inputs = step_inputs(env_state.obs, agent)
        core, action, _, _ = act(networks, params, target_feats, agent, env_state.obs, k)
        record = (inputs, truth(env_state.obs))
        env_state = env.step(env_state, action, world)
        step_record = (action, env_state.reward, env_state.terminated, env_state.truncated)
        return (env_state, observe(core, action, env_state)), (record, step_record, episode_stats(env_state))

    (env_state, agent_out), (recs, step_records, stats) = jax.lax.scan(
        step, (env_state, agent), jax.random.split(key, steps))
    last = (step_inputs(env_state.obs, agent_out), truth(env_state.obs))
    (inputs, frame_truth) = jax.tree_util.tree_map(lambda seq, x: jnp.concatenate([seq, x[None]]), recs, last)
    stats = {k: v.sum() for k, v in stats.items()}
    return Transition.of(inputs, *step_records), frame_truth, env_state, agent_out, stats
