"""A2CAT-VN: batched A2C with an off-policy critic, UNREAL and visual-navigation
auxiliary tasks, in one jit-compiled update.

`Learner.update(train_state) -> (train_state, metrics)` does everything of one update
inside `jax.jit`:

1. collect a rollout of `rollout_length` steps in all B environments (the policy
   samples, the environment steps and renders);
2. write it to the replay buffer (when a replay loss is on);
3. compute the losses: actor, critic and entropy on the rollout with returns
   bootstrapped at its end (paper eq. 1-3); off-policy critic and pixel control on
   sequences sampled from the replay buffer; reward prediction on replay windows
   balanced between zero and non-zero final reward; depth, observation and target
   segmentation on the rollout's frames;
4. sum them with the configured weights, clip the global gradient norm and apply
   RMSprop with the (linearly decaying) learning rate.

A loss whose weight is 0 is not traced at all, so plain A2C, A2C+UNREAL and A2CAT-VN
are three configurations of this one code path; with no replay loss on there is no
replay buffer either.

The memory core's state is carried from one rollout to the next and cleared at the
first step of every episode. With `train.curriculum` the environment's complexity tau
follows a linear schedule in the frame count, set at the start of every update (data,
not a compile-time constant). Sequences are time-major: `[T, B, ...]`.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Optional

import jax
import jax.numpy as jnp
import optax
from flax import struct

from a2catvn_jax.agent import losses, networks
from a2catvn_jax.agent import replay as replay_lib
from a2catvn_jax.config import Config
from a2catvn_jax.env import NavEnv
from a2catvn_jax.env.scenes.spec import NUM_CLASSES
from a2catvn_jax.env.world import SEGMENTATION_COLORS

DEPTH_SCALE = 0.1  # depth targets are metres * DEPTH_SCALE
INPUT_FIELDS = ("rgb", "target", "prev_action", "prev_reward", "reset")  # [T+1, B] network inputs
STEP_FIELDS = ("action", "reward", "done")  # [T, B]
REPLAY_FIELDS = INPUT_FIELDS + STEP_FIELDS


@struct.dataclass
class AgentState:
    """What the agent carries between steps, per environment [B]."""

    carry: Any  # memory core state
    prev_action: jnp.ndarray  # int32
    prev_reward: jnp.ndarray  # float32
    reset: jnp.ndarray  # bool: clear the core state before the next step (a new episode began)


@struct.dataclass
class TrainState:
    params: Any
    opt_state: Any
    env_state: Any
    agent: AgentState
    replay: Optional[replay_lib.Replay]
    key: jnp.ndarray  # uint32 [2]
    update: jnp.ndarray  # int32: updates done so far


class Learner:
    """The network, the optimiser and the jitted update for one configuration."""

    def __init__(self, cfg: Config, env: Optional[NavEnv] = None):
        self.cfg = cfg
        self.env = env if env is not None else NavEnv(cfg.env)
        tc = cfg.train
        self.weights = tc.loss_weights
        self.T = tc.rollout_length
        self.B = self.env.num_envs
        self.frames_per_update = self.T * self.B
        self.total_updates = math.ceil(tc.total_frames / self.frames_per_update)
        size = cfg.env.render.image_size
        self.net = networks.A2CATNet(
            cfg.agent, self.env.num_actions, size, tc.pixel_control_cell, tc.aux_downsize, NUM_CLASSES
        )
        w = self.weights
        self.uses_replay = w.off_policy_critic > 0 or w.pixel_control > 0 or w.reward_prediction > 0
        self.replay_slots = max(1, tc.replay_size // self.T)

        arrays = self.env.world.arrays
        S, G = arrays.target_rgb.shape[:2]
        self.goals_per_scene = G
        self._colors = jnp.asarray(SEGMENTATION_COLORS, jnp.float32) / 255.0
        self.target_rgb = arrays.target_rgb.reshape((S * G,) + arrays.target_rgb.shape[2:])
        self.target_seg_gt = self._seg_targets(arrays.target_seg.reshape((S * G,) + arrays.target_seg.shape[2:]))

        self.schedule = (
            optax.linear_schedule(tc.learning_rate, 0.0, self.total_updates)
            if tc.lr_schedule == "linear"
            else optax.constant_schedule(tc.learning_rate)
        )
        self.optimizer = optax.chain(
            optax.clip_by_global_norm(tc.max_grad_norm),
            optax.rmsprop(self.schedule, decay=tc.rmsprop_decay, eps=tc.rmsprop_eps, eps_in_sqrt=False),
        )
        self.update = jax.jit(self._update, donate_argnums=0)
        self.init = jax.jit(self._init)

    # -- state ----------------------------------------------------------------------------

    def init_params(self, key):
        """Freshly initialised network parameters."""
        size = self.cfg.env.render.image_size
        img = jnp.zeros((1, size, size, 3), jnp.uint8)
        return self.net.init(key, img, img, jnp.zeros((1,), jnp.int32), jnp.zeros((1,)))

    def _init(self, key) -> TrainState:
        k_param, k_env, k_train = jax.random.split(key, 3)
        params = self.init_params(k_param)
        env_state = self.env.reset(k_env, complexity=self.complexity(0))
        replay = None
        if self.uses_replay:
            example = self._replay_example()
            replay = replay_lib.init(example, self.initial_agent().carry, self.replay_slots)
        return TrainState(params, self.optimizer.init(params), env_state, self.initial_agent(), replay, k_train,
                          jnp.zeros((), jnp.int32))

    def initial_agent(self, batch: Optional[int] = None) -> AgentState:
        B = self.B if batch is None else batch
        carry = self.net.apply({}, B, method=networks.A2CATNet.initial_carry)
        return AgentState(carry, jnp.zeros((B,), jnp.int32), jnp.zeros((B,), jnp.float32), jnp.ones((B,), bool))

    def _replay_example(self) -> dict:
        size = self.cfg.env.render.image_size
        L, B = self.T + 1, self.B
        ex = {
            "rgb": jnp.zeros((L, B, size, size, 3), jnp.uint8),
            "target": jnp.zeros((L, B), jnp.int32),
            "prev_action": jnp.zeros((L, B), jnp.int32),
            "prev_reward": jnp.zeros((L, B), jnp.float32),
            "reset": jnp.zeros((L, B), bool),
        }
        ex.update(action=jnp.zeros((L - 1, B), jnp.int32), reward=jnp.zeros((L - 1, B), jnp.float32),
                  done=jnp.zeros((L - 1, B), bool))
        return ex

    def shard(self, ts: TrainState, mesh, axis: str = "batch") -> TrainState:
        """`ts` placed on `mesh` with its environment axis split over the mesh axis `axis`
        (environment and agent state, the replay buffer's environment axis) and everything
        else replicated. `update` keeps that layout: each device steps, renders and runs the
        network for its share of the environments, and gradients are reduced across them."""
        from jax.sharding import NamedSharding, PartitionSpec

        tm = jax.tree_util.tree_map
        replicated = NamedSharding(mesh, PartitionSpec())

        def along(dim):
            return lambda _: NamedSharding(mesh, PartitionSpec(*([None] * dim), axis))

        replay = None
        if ts.replay is not None:
            replay = replay_lib.Replay(tm(along(2), ts.replay.data), tm(along(1), ts.replay.carry), replicated)
        spec = TrainState(tm(lambda _: replicated, ts.params), tm(lambda _: replicated, ts.opt_state),
                          tm(along(0), ts.env_state), tm(along(0), ts.agent), replay, replicated, replicated)
        return jax.device_put(ts, spec)

    def frames(self, ts: TrainState):
        return ts.update * self.frames_per_update

    def complexity(self, frames):
        """Curriculum complexity tau after `frames` frames (paper: 0.3 -> 1.0 from 5M to 10M frames)."""
        tc = self.cfg.train
        if not tc.curriculum:
            return jnp.float32(self.cfg.env.complexity)
        (t0, t1), (f0, f1) = tc.curriculum_complexity, tc.curriculum_frames
        frac = jnp.clip((jnp.asarray(frames, jnp.float32) - f0) / max(f1 - f0, 1), 0.0, 1.0)
        return jnp.float32(t0) + (t1 - t0) * frac

    # -- acting -----------------------------------------------------------------------------

    def target_features(self, params):
        """Target-stream features of every distinct target image [S*G, g, g, c2]."""
        return self.net.apply(params, self.target_rgb, method=networks.A2CATNet.target_stream)

    def inputs(self, env_state, agent: AgentState) -> dict:
        """Network inputs of the current step, per environment."""
        info = env_state.info
        return {
            "rgb": env_state.obs["rgb"],
            "target": info["scene"] * self.goals_per_scene + info["goal"],
            "prev_action": agent.prev_action,
            "prev_reward": agent.prev_reward,
            "reset": agent.reset,
        }

    def _clear(self, carry, reset):
        init = self.net.apply({}, reset.shape[0], method=networks.A2CATNet.initial_carry)
        return jax.tree_util.tree_map(lambda c, z: jnp.where(reset.reshape((-1,) + (1,) * (c.ndim - 1)), z, c), carry, init)

    def policy(self, params, target_feats, carry, inputs):
        """One step: (new core state, logits [N, A], value [N])."""
        _, feats = self.net.apply(params, inputs["rgb"], target_feats[inputs["target"]], method=networks.A2CATNet.encode)
        carry = self._clear(carry, inputs["reset"])
        carry, out = self.net.apply(params, carry, feats, inputs["prev_action"], inputs["prev_reward"],
                                    method=networks.A2CATNet.core)
        logits, value = self.net.apply(params, out, method=networks.A2CATNet.actor_critic)
        return carry, logits, value

    def act(self, params, target_feats, agent: AgentState, env_state, key, greedy: bool = False):
        """(next agent state before the environment step, action [B], logits, value)."""
        inputs = self.inputs(env_state, agent)
        carry, logits, value = self.policy(params, target_feats, agent.carry, inputs)
        action = jnp.argmax(logits, -1) if greedy else jax.random.categorical(key, logits)
        return carry, action.astype(jnp.int32), logits, value

    def observe(self, carry, action, env_state) -> AgentState:
        """Agent state after the environment answered `action` with `env_state`."""
        return AgentState(carry, action, env_state.reward, env_state.done)

    def _seg_targets(self, seg):
        """Segmentation ground truth at auxiliary resolution: class colours or class ids."""
        f = self.cfg.train.aux_downsize
        if self.cfg.agent.segmentation_loss == "cross_entropy":
            return losses.downsize_pick(seg, f).astype(jnp.int32)
        return losses.downsize_mean(self._colors[seg], f)

    def frame_targets(self, obs: dict) -> dict:
        """Depth and segmentation ground truth at auxiliary resolution of frames
        (obs["depth"], obs["segmentation"] [N, H, W]), for the losses that are on."""
        out = {}
        if self.weights.depth > 0:
            out["depth_gt"] = losses.downsize_mean(obs["depth"], self.cfg.train.aux_downsize) * DEPTH_SCALE
        if self.weights.segmentation > 0:
            out["seg_gt"] = self._seg_targets(obs["segmentation"])
        return out

    def _rollout(self, params, env_state, agent: AgentState, key):
        """T steps in all environments: (trajectory, env state, agent state, episode stats)."""
        target_feats = self.target_features(params)

        def step(carry, k):
            env_state, agent = carry
            inputs = self.inputs(env_state, agent)
            core, action, _, _ = self.act(params, target_feats, agent, env_state, k)
            record = dict(inputs, **self.frame_targets(env_state.obs))
            env_state = self.env.step(env_state, action)
            m = env_state.metrics
            done = env_state.done
            stats = {
                "episodes": done.sum(),
                "successes": (m["success"] & done).sum(),
                "length_sum": jnp.where(done, m["episode_length"], 0).sum(),
                "spl_sum": jnp.where(done, m["episode_spl"], 0.0).sum(),
                "return_sum": jnp.where(done, m["episode_return"], 0.0).sum(),
            }
            step_rec = {"action": action, "reward": env_state.reward, "done": done}
            return (env_state, self.observe(core, action, env_state)), (record, step_rec, stats)

        (env_state, agent_out), (recs, steps, stats) = jax.lax.scan(step, (env_state, agent), jax.random.split(key, self.T))
        last = dict(self.inputs(env_state, agent_out), **self.frame_targets(env_state.obs))
        traj = jax.tree_util.tree_map(lambda seq, x: jnp.concatenate([seq, x[None]]), recs, last)
        traj.update(steps)
        stats = {k: v.sum() for k, v in stats.items()}
        return traj, env_state, agent_out, stats

    # -- learning -------------------------------------------------------------------------

    def unroll(self, params, target_feats, seq: dict, carry0):
        """Network over a sequence [L, N]: (conv4 maps [L, N, ...], core outputs [L, N, core])."""
        L, N = seq["rgb"].shape[:2]
        flat = lambda x: x.reshape((L * N,) + x.shape[2:])  # noqa: E731
        conv4, feats = self.net.apply(params, flat(seq["rgb"]), target_feats[flat(seq["target"])],
                                      method=networks.A2CATNet.encode)
        feats = feats.reshape(L, N, -1)

        def body(carry, x):
            f, prev_action, prev_reward, reset = x
            carry = self._clear(carry, reset)
            return self.net.apply(params, carry, f, prev_action, prev_reward, method=networks.A2CATNet.core)

        _, outs = jax.lax.scan(body, carry0, (feats, seq["prev_action"], seq["prev_reward"], seq["reset"]))
        return conv4.reshape((L, N) + conv4.shape[1:]), outs

    def _apply_flat(self, params, method, x, lead: int = 2):
        """Apply a head to [L, N, ...] inputs by flattening the leading axes."""
        shape = x.shape[:lead]
        y = self.net.apply(params, x.reshape((-1,) + x.shape[lead:]), method=method)
        return jax.tree_util.tree_map(lambda a: a.reshape(shape + a.shape[1:]), y)

    def loss(self, params, traj: dict, carry0, replay: Optional[replay_lib.Replay], key):
        """(total loss, per-term losses) of one rollout (and replay samples)."""
        tc, w = self.cfg.train, self.weights
        Net = networks.A2CATNet
        target_feats = self.target_features(params)
        conv4, out = self.unroll(params, target_feats, traj, carry0)
        logits, values = self._apply_flat(params, Net.actor_critic, out)
        returns = losses.bootstrapped_returns(traj["reward"], traj["done"], jax.lax.stop_gradient(values[-1]), tc.gamma)
        actor, critic, neg_entropy = losses.actor_critic_losses(logits[:-1], values[:-1], traj["action"], returns)
        terms = {"actor": actor, "critic": critic, "entropy": neg_entropy}
        terms.update(self.vn_losses(params, conv4, traj, traj["target"]))
        if replay is not None:
            terms.update(self._replay_losses(params, target_feats, replay, key))
        total = sum(getattr(w, name) * value for name, value in terms.items())
        return total, terms

    def vn_losses(self, params, conv4, truth: dict, target_index) -> dict:
        """Depth, observation and target segmentation losses (those with a non-zero weight)
        of conv4 maps [..., g, g, c4] against `truth` ("depth_gt", "seg_gt") and the
        ground truth of the targets `target_index` [...]."""
        heads = tuple(h for h in networks.VN_HEADS if getattr(self.weights, h) > 0)
        if not heads:
            return {}
        seg_loss = losses.cross_entropy if self.cfg.agent.segmentation_loss == "cross_entropy" else losses.mse
        method = functools.partial(networks.A2CATNet.vn_heads, heads=heads)
        pred = self._apply_flat(params, method, conv4, conv4.ndim - 3)
        terms = {}
        if "depth" in pred:
            terms["depth"] = losses.mse(pred["depth"], truth["depth_gt"])
        if "segmentation" in pred:
            terms["segmentation"] = seg_loss(pred["segmentation"], truth["seg_gt"])
        if "target_segmentation" in pred:
            terms["target_segmentation"] = seg_loss(pred["target_segmentation"], self.target_seg_gt[target_index])
        return terms

    def _replay_losses(self, params, target_feats, replay: replay_lib.Replay, key) -> dict:
        tc, w = self.cfg.train, self.weights
        Net = networks.A2CATNet
        k_seq, k_rp = jax.random.split(key)
        terms = {}
        n = tc.replay_batch
        if w.off_policy_critic > 0 or w.pixel_control > 0:
            seq, carry0 = replay_lib.sample_sequences(replay, k_seq, n, REPLAY_FIELDS)
            _, out = self.unroll(params, target_feats, seq, carry0)
            if w.off_policy_critic > 0:
                _, values = self._apply_flat(params, Net.actor_critic, out)
                returns = losses.bootstrapped_returns(seq["reward"], seq["done"], jax.lax.stop_gradient(values[-1]), tc.gamma)
                terms["off_policy_critic"] = jnp.mean(0.5 * jnp.square(returns - values[:-1]))
            if w.pixel_control > 0:
                q = self._apply_flat(params, Net.pixel_control, out)
                pc = jax.vmap(losses.pixel_control_loss, in_axes=(1, 1, 1, 1, None, None))(
                    seq["rgb"], seq["action"], seq["done"], q, tc.pixel_control_gamma, tc.pixel_control_cell
                )
                terms["pixel_control"] = jnp.mean(pc)
        if w.reward_prediction > 0:
            frames = networks.RP_FRAMES
            win, reward = replay_lib.sample_reward_windows(replay, k_rp, n, frames, ("rgb", "target"))
            flat = lambda x: x.reshape((n * frames,) + x.shape[2:])  # noqa: E731
            conv4, _ = self.net.apply(params, flat(win["rgb"]), target_feats[flat(win["target"])], method=Net.encode)
            logits = self.net.apply(params, conv4.reshape((n, frames) + conv4.shape[1:]), method=Net.reward_prediction)
            terms["reward_prediction"] = losses.cross_entropy(logits, networks.reward_class(reward))
        return terms

    def _update(self, ts: TrainState):
        key, k_roll, k_loss = jax.random.split(ts.key, 3)
        carry0 = ts.agent.carry
        tau = self.complexity(self.frames(ts))
        env_state = self.env.set_complexity(ts.env_state, tau) if self.cfg.train.curriculum else ts.env_state
        traj, env_state, agent, stats = self._rollout(ts.params, env_state, ts.agent, k_roll)
        replay = ts.replay
        if replay is not None:
            replay = replay_lib.add(replay, {k: traj[k] for k in REPLAY_FIELDS}, carry0)
        (total, terms), grads = jax.value_and_grad(self.loss, has_aux=True)(ts.params, traj, carry0, replay, k_loss)
        updates, opt_state = self.optimizer.update(grads, ts.opt_state, ts.params)
        params = optax.apply_updates(ts.params, updates)
        metrics = {f"loss/{k}": v for k, v in terms.items()}
        metrics.update({
            "loss/total": total,
            "grad_norm": optax.tree.norm(grads),
            "learning_rate": self.schedule(ts.update),
            "complexity": tau,
            **stats,
        })
        new = TrainState(params, opt_state, env_state, agent, replay, key, ts.update + 1)
        return new, metrics
