"""A2CAT-VN's training step: batched A2C with an off-policy critic, UNREAL and
visual-navigation auxiliary tasks, in one jit-compiled update.

`make_update(env, networks, cfg)` returns `(init, update)`:
`init(key) -> TrainState` and `update(TrainState) -> (TrainState, metrics)`, which does
everything of one update inside `jax.jit`:

1. collect a rollout of `rollout_length` steps in all B environments (the policy
   samples, the environment steps and renders; `acting.rollout`);
2. write it to the replay buffer (when a replay loss is on);
3. compute the losses (`losses.py`): actor, critic and entropy on the rollout with
   returns bootstrapped at its end (paper eq. 1-3); off-policy critic and pixel
   control on sequences sampled from the replay buffer; reward prediction on replay
   windows with a set share (`train.reward_prediction_zero_fraction`) ending with zero
   reward; depth, observation and target segmentation on the rollout's frames;
4. sum them with the configured weights, clip the global gradient norm and apply
   RMSprop with the (linearly decaying) learning rate.

A loss whose weight is 0 is not traced at all, so plain A2C, A2C+UNREAL and A2CAT-VN
are three configurations of this one code path; with no replay loss on there is no
replay buffer either. With `train.replay_warmup`, `init` fills the buffer with the
initial policy's rollouts before the first update (`warmup`); those frames are not
counted.

The memory core's state is carried from one rollout to the next and cleared at the
first step of every episode. With `train.curriculum` the environment's complexity tau
follows a linear schedule in the frame count, set at the start of every update (data,
not a compile-time constant). Sequences are time-major: `[T, B, ...]`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import NamedSharding, PartitionSpec

from a2catvn_jax.agent import losses
from a2catvn_jax.agent import replay as replay_lib
from a2catvn_jax.agent.acting import actor_critic_sequence, initial_agent, rollout, unroll
from a2catvn_jax.agent.networks import RP_FRAMES, SHARED_LAYERS, VN_HEADS, Networks, Params, apply_flat
from a2catvn_jax.agent.types import FrameTruth, TrainState, Transition
from a2catvn_jax.config import Config
from a2catvn_jax.env.scenes.spec import SEGMENTATION_COLORS


def frames_per_update(cfg: Config) -> int:
    """Agent steps one update collects: rollout length x environments."""
    return cfg.train.rollout_length * cfg.env.num_envs


def total_updates(cfg: Config) -> int:
    """Updates of a whole run: `train.total_frames` rounded up to whole updates."""
    return math.ceil(cfg.train.total_frames / frames_per_update(cfg))


def uses_replay(cfg: Config) -> bool:
    w = cfg.train.loss_weights
    return w.off_policy_critic > 0 or w.pixel_control > 0 or w.reward_prediction > 0


def vn_heads_on(cfg: Config) -> tuple[str, ...]:
    """The depth / segmentation heads whose loss has a non-zero weight."""
    return tuple(h for h in VN_HEADS if getattr(cfg.train.loss_weights, h) > 0)


REFERENCE_ENVS = 16  # `train.lr_scaling` scales the learning rate relative to the paper's 16 environments


def learning_rate(cfg: Config) -> float:
    """`train.learning_rate`, scaled with the batch (`train.lr_scaling`): times b / 16
    (linear) or sqrt(b / 16) (sqrt), b the environments of one gradient step (all of
    the run's, or their share with `train.minibatches`)."""
    tc = cfg.train
    ratio = cfg.env.num_envs / tc.minibatches / REFERENCE_ENVS
    return tc.learning_rate * {"none": 1.0, "linear": ratio, "sqrt": math.sqrt(ratio)}[tc.lr_scaling]


def learning_rate_schedule(cfg: Config) -> optax.Schedule:
    """The rate at gradient step n (`train.minibatches` steps per update): lr * (f_max -
    f) / f_max (paper), or a constant; lr scaled by `learning_rate`; with
    `train.lr_warmup_frames` W, times min(1, (n + 1) / ceil(W / frames per step)) (a
    linear warm-up, for large batches)."""
    lr, steps = learning_rate(cfg), cfg.train.minibatches
    if cfg.train.lr_schedule == "linear":
        base = optax.linear_schedule(lr, 0.0, total_updates(cfg) * steps)
    else:
        base = optax.constant_schedule(lr)
    warmup = -(-cfg.train.lr_warmup_frames * steps // frames_per_update(cfg))
    if warmup <= 1:
        return base
    return lambda n: base(n) * jnp.minimum(1.0, (n + 1) / warmup)


def make_optimizer(cfg: Config) -> optax.GradientTransformation:
    """Global gradient-norm clipping, then RMSprop (eps outside the square root; the
    paper's), Adam or LAMB (`train.optimizer`)."""
    tc = cfg.train
    schedule = learning_rate_schedule(cfg)
    step = {
        "rmsprop": lambda: optax.rmsprop(schedule, decay=tc.rmsprop_decay, eps=tc.rmsprop_eps, eps_in_sqrt=False),
        "adam": lambda: optax.adam(schedule, eps=tc.rmsprop_eps),
        "lamb": lambda: optax.lamb(schedule, eps=tc.rmsprop_eps),
    }[tc.optimizer]()
    return optax.chain(optax.clip_by_global_norm(tc.max_grad_norm), step)


@dataclasses.dataclass(frozen=True)
class Learner:
    """What the update's losses and rollout need from the configuration, read once
    (`learner(cfg)`): the functions below take these values, not the config tree."""

    rollout_length: int
    image_size: int
    frames_per_update: int
    minibatches: int  # gradient steps per rollout, each on an equal share of the environments
    gamma: float
    weights: tuple[tuple[str, float], ...]  # (loss term, weight) of every term with a non-zero weight
    vn_heads: tuple[str, ...]  # the depth / segmentation heads whose loss is on
    replay: bool  # a replay loss is on (so there is a replay buffer)
    timeout_bootstrap: bool  # a time-out bootstraps the returns from the critic
    colors: Optional[tuple]  # segmentation targets' class colours in [0, 1], or None for class ids
    aux_downsize: int
    aux_every: int
    remat_vision_heads: bool
    replay_batch: int
    pixel_control_gamma: float
    pixel_control_cell: int
    pixel_control_reward: str
    reward_prediction_loss: str
    reward_prediction_zero_fraction: float
    reward_prediction_target: str
    complexity: float  # the environment's complexity without a curriculum
    curriculum: Optional[tuple[tuple[float, float], tuple[int, int]]]  # (complexities, frame counts) or None

    def weight(self, term: str) -> float:
        return dict(self.weights).get(term, 0.0)


def learner(cfg: Config) -> Learner:
    """The `Learner` of configuration `cfg`."""
    tc, w = cfg.train, cfg.train.loss_weights
    colors = segmentation_colors(cfg)
    return Learner(
        rollout_length=tc.rollout_length, image_size=cfg.env.render.image_size,
        frames_per_update=frames_per_update(cfg), minibatches=tc.minibatches, gamma=tc.gamma,
        weights=tuple((f.name, getattr(w, f.name)) for f in dataclasses.fields(w) if getattr(w, f.name) > 0),
        vn_heads=vn_heads_on(cfg), replay=uses_replay(cfg), timeout_bootstrap=tc.timeout_bootstrap,
        colors=None if colors is None else tuple(map(tuple, colors.tolist())),
        aux_downsize=tc.aux_downsize, aux_every=tc.aux_every, remat_vision_heads=tc.remat_vision_heads,
        replay_batch=tc.replay_batch, pixel_control_gamma=tc.pixel_control_gamma,
        pixel_control_cell=tc.pixel_control_cell, pixel_control_reward=tc.pixel_control_reward,
        reward_prediction_loss=tc.reward_prediction_loss,
        reward_prediction_zero_fraction=tc.reward_prediction_zero_fraction,
        reward_prediction_target=tc.reward_prediction_target, complexity=cfg.env.complexity,
        curriculum=(tuple(tc.curriculum_complexity), tuple(tc.curriculum_frames)) if tc.curriculum else None,
    )


def complexity(spec: Learner, frames):
    """Curriculum complexity tau after `frames` frames (paper: 0.3 -> 1.0 from 5M to 10M frames)."""
    if spec.curriculum is None:
        return jnp.float32(spec.complexity)
    (t0, t1), (f0, f1) = spec.curriculum
    frac = jnp.clip((jnp.asarray(frames, jnp.float32) - f0) / max(f1 - f0, 1), 0.0, 1.0)
    return jnp.float32(t0) + (t1 - t0) * frac


def timeouts(spec: Learner, traj: Transition):
    """The steps [T, N] whose time-out the returns bootstrap from the critic at, or None
    when a time-out is terminal (`train.timeout_bootstrap=false`: the paper's returns)."""
    return traj.truncated if spec.timeout_bootstrap else None


def segmentation_colors(cfg: Config):
    """The class colours [C, 3] in [0, 1] that segmentation targets are encoded with, or
    None for class-id targets (`agent.segmentation_loss=cross_entropy`)."""
    if cfg.agent.segmentation_loss == "cross_entropy":
        return None
    return np.asarray(SEGMENTATION_COLORS, np.float32) / 255.0


def _colors(spec: Learner):
    return None if spec.colors is None else jnp.asarray(spec.colors, jnp.float32)


def frame_truth(spec: Learner, depth, segmentation) -> FrameTruth:
    """Depth and segmentation ground truth of frames (depth [N, H, W] metres,
    segmentation [N, H, W] class ids) at auxiliary resolution, for the losses that are on."""
    heads, f = spec.vn_heads, spec.aux_downsize
    depth = losses.depth_targets(depth, f) if "depth" in heads else None
    seg = losses.segmentation_targets(segmentation, f, _colors(spec)) if "segmentation" in heads else None
    return FrameTruth(depth, seg)


def vn_terms(spec: Learner, networks: Networks, params: Params, conv4, truth: FrameTruth, target_seg, every: int = 1,
             remat: bool = False) -> dict:
    """Depth, observation and target segmentation losses (those with a non-zero weight)
    of conv4 maps [N, ..., g, g, c4] against `truth` and the targets' segmentation
    truth `target_seg` [N, ..., a, a(, 3)], on every `every`-th entry of the leading axis
    (a rollout's time axis: `train.aux_every`). With `remat` (`train.remat_vision_heads`)
    the heads run one entry of that axis at a time and again in the backward pass
    instead of keeping their activations."""
    heads = spec.vn_heads
    if not heads:
        return {}
    if every > 1:
        conv4, target_seg = conv4[::every], target_seg[::every]
        truth = jax.tree_util.tree_map(lambda a: a[::every], truth)

    def terms_of(params, conv4, truth, target_seg):
        pred = apply_flat(lambda x: networks.vn_heads(params, x, heads), conv4, conv4.ndim - 3)
        terms = {}
        if "depth" in pred:
            terms["depth"] = losses.mse(pred["depth"], truth.depth)
        if "segmentation" in pred:
            terms["segmentation"] = losses.segmentation_loss(pred["segmentation"], truth.segmentation)
        if "target_segmentation" in pred:
            terms["target_segmentation"] = losses.segmentation_loss(pred["target_segmentation"], target_seg)
        return terms

    if not remat:
        return terms_of(params, conv4, truth, target_seg)
    # One rollout step at a time, each step's heads run again in the backward pass: only
    # one step's activations are live at once. Every step has as many frames, so the mean
    # over steps of each step's mean is the mean over all frames.
    step = jax.checkpoint(functools.partial(terms_of, params))
    per_step = jax.lax.map(lambda xs: step(*xs), (conv4, truth, target_seg))
    return {name: jnp.mean(value) for name, value in per_step.items()}


def replay_terms(spec: Learner, networks: Networks, params: Params, target_feats, replay: replay_lib.Replay,
                 key) -> dict:
    """Off-policy critic, pixel control and reward prediction losses (those with a
    non-zero weight) on sequences and windows sampled from the replay buffer."""
    k_seq, k_rp = jax.random.split(key)
    terms = {}
    n = spec.replay_batch
    on = dict(spec.weights)
    if "off_policy_critic" in on or "pixel_control" in on:
        seq, carry0 = replay_lib.sample_sequences(replay, k_seq, n)
        _, out = unroll(networks, params, target_feats, seq.inputs, carry0)
        if "off_policy_critic" in on:
            _, values = actor_critic_sequence(networks, params, out)
            terms["off_policy_critic"] = losses.off_policy_critic_loss(values, seq.reward, seq.done, spec.gamma,
                                                                       timeouts(spec, seq))
        if "pixel_control" in on:
            q = apply_flat(lambda x: networks.pixel_control(params, x), out)
            pc_loss = functools.partial(losses.pixel_control_loss, gamma=spec.pixel_control_gamma,
                                        cell=spec.pixel_control_cell, reward=spec.pixel_control_reward)
            terms["pixel_control"] = jnp.mean(jax.vmap(pc_loss, in_axes=1)(seq.rgb, seq.action, seq.done, q))
    if "reward_prediction" in on:
        data = replay.data
        # "next_frame": windows of RP_FRAMES + 1 steps in one episode, the head sees the first RP_FRAMES.
        frames = RP_FRAMES + (spec.reward_prediction_target == "next_frame")
        win, reward = replay_lib.sample_reward_windows(replay, k_rp, n, frames, data.reward, data.reset,
                                                       spec.reward_prediction_zero_fraction)
        flat = lambda x: x[:, :RP_FRAMES].reshape((n * RP_FRAMES,) + x.shape[2:])  # noqa: E731
        conv4, _ = networks.encode(params, flat(win.rgb), target_feats[flat(win.target)])
        logits = networks.reward_prediction(params, conv4.reshape((n, RP_FRAMES) + conv4.shape[1:]))
        terms["reward_prediction"] = losses.reward_prediction_loss(logits, reward, spec.reward_prediction_loss)
    return terms


def transition_example(cfg: Config, batch: int) -> Transition:
    """A rollout of zeros, shaped and typed as `acting.rollout` gives them."""
    L, size = cfg.train.rollout_length + 1, cfg.env.render.image_size
    zeros = lambda shape, dtype: jnp.zeros(shape, dtype)  # noqa: E731
    return Transition(
        rgb=zeros((L, batch, size, size, 3), jnp.uint8), target=zeros((L, batch), jnp.int32),
        prev_action=zeros((L, batch), jnp.int32), prev_reward=zeros((L, batch), jnp.float32),
        reset=zeros((L, batch), bool), action=zeros((L - 1, batch), jnp.int32),
        reward=zeros((L - 1, batch), jnp.float32), terminated=zeros((L - 1, batch), bool),
        truncated=zeros((L - 1, batch), bool),
    )


class Targets(NamedTuple):
    """The distinct target images [K, H, W, 3] uint8 and their segmentation truth at
    auxiliary resolution [K, a, a(, 3)] (`Inputs.target` indexes both)."""

    rgb: jnp.ndarray
    segmentation: jnp.ndarray


def targets_of(spec: Learner, env, world=None) -> Targets:
    """The target images of `env`'s world (or of `world`, arrays of the same shapes)."""
    images = env.target_images(world)
    return Targets(images["rgb"], losses.segmentation_targets(images["segmentation"], spec.aux_downsize, _colors(spec)))


def loss(spec: Learner, networks: Networks, targets: Targets, params: Params, traj: Transition, truth: FrameTruth,
         carry0, replay: Optional[replay_lib.Replay], key):
    """(total loss, per-term losses) of one rollout `traj` [T(+1), B] started from core state
    `carry0`, its frames' ground truth, and (when given) samples of the replay buffer."""
    traj.check(spec.rollout_length, traj.action.shape[1], spec.image_size)
    target_feats = networks.target_stream(params, targets.rgb)
    conv4, out = unroll(networks, params, target_feats, traj.inputs, carry0)
    logits, values = actor_critic_sequence(networks, params, out)
    held = jax.lax.stop_gradient(values)
    returns = losses.bootstrapped_returns(traj.reward, traj.done, held[-1], spec.gamma, timeouts(spec, traj), held[:-1])
    actor, critic, neg_entropy = losses.actor_critic_losses(logits[:-1], values[:-1], traj.action, returns)
    terms = {"actor": actor, "critic": critic, "entropy": neg_entropy}
    terms.update(vn_terms(spec, networks, params, conv4, truth, targets.segmentation[traj.target], spec.aux_every,
                          spec.remat_vision_heads))
    if replay is not None:
        terms.update(replay_terms(spec, networks, params, target_feats, replay, key))
    total = sum(spec.weight(name) * value for name, value in terms.items())
    return total, terms


class Batch(NamedTuple):
    """What one update learns from: the rollout it collected and the state after it."""

    traj: Transition
    truth: FrameTruth
    carry0: object  # the core state the rollout started from
    replay: Optional[replay_lib.Replay]  # with the rollout written
    loss_key: jnp.ndarray
    env_state: object
    agent: object
    stats: dict
    key: jnp.ndarray  # the train state's next key
    complexity: jnp.ndarray

    @property
    def loss_args(self):
        """The arguments of `loss` after the parameters."""
        return self.traj, self.truth, self.carry0, self.replay, self.loss_key


def collect(spec: Learner, env, networks: Networks, targets: Targets, ts: TrainState, world=None) -> Batch:
    """The rollout of the update that follows `ts` (in `world`, default: the environment's
    own), written to the replay buffer (pure: `ts` is not changed, so a diagnostic can
    collect the same batch the update will)."""
    key, k_roll, k_loss = jax.random.split(ts.key, 3)
    tau = complexity(spec, ts.update * spec.frames_per_update)
    env_state = env.set_complexity(ts.env_state, tau) if spec.curriculum is not None else ts.env_state
    target_feats = networks.target_stream(ts.params, targets.rgb)
    truth = lambda obs: frame_truth(spec, obs.depth, obs.segmentation)  # noqa: E731
    traj, truth_seq, env_state, agent, stats = rollout(env, networks, ts.params, target_feats, env_state, ts.agent,
                                                       k_roll, spec.rollout_length, truth, world)
    replay = ts.replay if ts.replay is None else replay_lib.add(ts.replay, traj, ts.agent.carry)
    return Batch(traj, truth_seq, ts.agent.carry, replay, k_loss, env_state, agent, stats, key, tau)


def warmup_rollouts(cfg: Config) -> int:
    """Rollouts `train.replay_warmup` collects before the first update: one fewer than the
    buffer holds, so that the first update's own rollout fills it (0 when it is off or
    there is no replay buffer)."""
    if not (cfg.train.replay_warmup and uses_replay(cfg)):
        return 0
    return max(1, cfg.train.replay_size // cfg.train.rollout_length) - 1


def warmup(spec: Learner, rollouts: int, env, networks: Networks, targets: Targets, ts: TrainState,
           world=None) -> TrainState:
    """`ts` after `rollouts` (`warmup_rollouts(cfg)`) rollouts of its policy written to the replay buffer:
    the environments, the agent's memory, the buffer and the key move on; the parameters,
    the optimiser state and the update count (so the frame count, the learning rate and
    the curriculum) do not."""

    def one(_, ts):
        batch = collect(spec, env, networks, targets, ts, world)
        return ts.replace(env_state=batch.env_state, agent=batch.agent, replay=batch.replay, key=batch.key)

    return jax.lax.fori_loop(0, rollouts, one, ts)


def make_grad_norms(env, networks: Networks, cfg: Config) -> Callable:
    """A jitted diagnostic `grad_norms(TrainState) -> metrics`: the norm of the gradient of
    each weighted loss term (and of their sum) on the conv layers every head shares
    (`networks.SHARED_LAYERS`), on the batch the next update will learn from. It changes
    no state; the training loop calls it every `train.grad_norm_every` updates (with
    `world`, the arrays of the houses the run is in, when they replace the environment's own)."""
    spec = learner(cfg)

    def grad_norms(ts: TrainState, world=None) -> dict:
        targets = targets_of(spec, env, world)
        batch = collect(spec, env, networks, targets, ts, world)

        def weighted_terms(params):
            _, terms = loss(spec, networks, targets, params, *batch.loss_args)
            return {name: spec.weight(name) * value for name, value in terms.items()}

        terms, vjp_fn = jax.vjp(weighted_terms, ts.params)
        shared = lambda g: optax.tree.norm({k: g["params"][k] for k in SHARED_LAYERS})  # noqa: E731
        out = {}
        for name in terms:
            (g,) = vjp_fn({m: jnp.ones_like(v) if m == name else jnp.zeros_like(v) for m, v in terms.items()})
            out[f"grad_norm/{name}"] = shared(g)
        out["grad_norm/total_shared"] = shared(vjp_fn(jax.tree_util.tree_map(jnp.ones_like, terms))[0])
        return out

    return jax.jit(grad_norms)


def minibatches(n: int, traj: Transition, truth: FrameTruth, carry0):
    """(traj, truth, carry0) split into `n` shares of the environments, stacked on a new
    leading axis: share m holds environments m, m + n, m + 2n, ... (a strided split, so
    that environments split over devices in contiguous blocks stay balanced)."""

    def split(x, axis):
        shape = x.shape[:axis] + (x.shape[axis] // n, n) + x.shape[axis + 1:]
        return jnp.moveaxis(x.reshape(shape), axis + 1, 0)

    time_major = lambda tree: jax.tree_util.tree_map(lambda x: split(x, 1), tree)  # noqa: E731
    return time_major(traj), time_major(truth), jax.tree_util.tree_map(lambda x: split(x, 0), carry0)


def steps_written_out() -> bool:
    """Whether an update writes its `train.minibatches` steps out one after another in its
    program (on the CPU) rather than looping over them (elsewhere, where the compile
    would grow with M). XLA's CPU backend runs the convolutions' weight gradients
    several times slower inside a loop (docs/benchmarks.md, "Minibatches")."""
    return jax.default_backend() == "cpu"


class UpdateFns(NamedTuple):
    """`init(key, params=None) -> TrainState` (fresh parameters unless given) and the
    jitted `update(TrainState, world=None) -> (TrainState, metrics)` (its state is
    donated; `world`: the arrays of houses that replace the environment's own, as
    `train.new_houses_every` does, of the same shapes)."""

    init: Callable
    update: Callable


def starter(env, networks: Networks, cfg: Config) -> Callable:
    """`start(ts, key, world=None) -> ts` with every environment at a new episode (in
    `world`, default: the environment's own houses) drawn with `key`, the agent's memory
    cleared and the replay buffer emptied, or filled by `warmup` with `train.replay_warmup`:
    how a run begins, and how it moves to new houses (`make_renew`)."""
    spec, tc, B = learner(cfg), cfg.train, env.num_envs
    replay_slots = max(1, tc.replay_size // tc.rollout_length)
    example = jax.eval_shape(lambda: transition_example(cfg, B))  # shapes only: nothing of the batch allocated here
    warmup_steps = warmup_rollouts(cfg)

    def start(ts: TrainState, key, world=None) -> TrainState:
        env_state = env.reset(key, complexity=complexity(spec, ts.update * spec.frames_per_update), world=world)
        agent = initial_agent(networks, B)
        replay = replay_lib.init(example, agent.carry, replay_slots, tc.replay_envs) if spec.replay else None
        ts = ts.replace(env_state=env_state, agent=agent, replay=replay)
        if warmup_steps:
            ts = warmup(spec, warmup_steps, env, networks, targets_of(spec, env, world), ts, world)
        return ts

    return start


def make_renew(env, networks: Networks, cfg: Config) -> Callable:
    """`renew(ts, world) -> ts` (not jitted): the run moved to the houses of `world`
    (arrays of the environment's shapes, `world.new_houses`), as `train.new_houses_every`
    does. Every environment begins a new episode there, the agent's memory is cleared
    and the replay buffer emptied (its target indices would name the old houses'
    images), refilled with `train.replay_warmup`; the parameters, the optimiser state
    and the update count are kept, and the key moves on."""
    start = starter(env, networks, cfg)

    def renew(ts: TrainState, world) -> TrainState:
        key, k_env = jax.random.split(ts.key)
        return start(ts.replace(key=key), k_env, world)

    return renew


def make_update(env, networks: Networks, cfg: Config) -> UpdateFns:
    """The jitted training step of configuration `cfg` in `env` (see the module docstring)."""
    spec = learner(cfg)
    optimizer = make_optimizer(cfg)
    schedule = learning_rate_schedule(cfg)
    targets = targets_of(spec, env)
    start = starter(env, networks, cfg)

    def init(key, params: Optional[Params] = None) -> TrainState:
        k_param, k_env, k_train = jax.random.split(key, 3)
        params = networks.init(k_param) if params is None else params
        ts = TrainState(params, optimizer.init(params), None, None, None, k_train, jnp.zeros((), jnp.int32))
        return start(ts, k_env)

    grad_fn = jax.value_and_grad(functools.partial(loss, spec, networks), argnums=1, has_aux=True)

    def step(targets, params, opt_state, traj, truth, carry0, replay, key):
        (total, terms), grads = grad_fn(targets, params, traj, truth, carry0, replay, key)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        metrics = {**{f"loss/{k}": v for k, v in terms.items()}, "loss/total": total, "grad_norm": optax.tree.norm(grads)}
        return optax.apply_updates(params, updates), opt_state, metrics

    def update(ts: TrainState, world=None):
        now = targets if world is None else targets_of(spec, env, world)
        batch = collect(spec, env, networks, now, ts, world)
        if spec.minibatches == 1:
            params, opt_state, metrics = step(now, ts.params, ts.opt_state, *batch.loss_args)
        else:  # one step per share of the environments, in turn, each from the last one's parameters
            parts = minibatches(spec.minibatches, batch.traj, batch.truth, batch.carry0)

            def one(carry, part):
                params, opt_state = carry
                (traj, truth, carry0), key = part
                params, opt_state, metrics = step(now, params, opt_state, traj, truth, carry0, batch.replay, key)
                return (params, opt_state), metrics

            keys = jax.random.split(batch.loss_key, spec.minibatches)
            (params, opt_state), metrics = jax.lax.scan(one, (ts.params, ts.opt_state), (parts, keys),
                                                        unroll=steps_written_out())
            metrics = jax.tree_util.tree_map(lambda m: jnp.mean(m, axis=0), metrics)
        metrics.update({
            "learning_rate": schedule(ts.update * spec.minibatches),
            "complexity": batch.complexity,
            **batch.stats,
        })
        return TrainState(params, opt_state, batch.env_state, batch.agent, batch.replay, batch.key, ts.update + 1), metrics

    return UpdateFns(jax.jit(init), jax.jit(update, donate_argnums=0))


def shard(ts: TrainState, mesh, axis: str = "batch") -> TrainState:
    """`ts` placed on `mesh` with its environment axis split over the mesh axis `axis`
    (environment and agent state, the replay buffer's environment axis) and everything
    else replicated. `update` keeps that layout: each device steps, renders and runs the
    network for its share of the environments, and gradients are reduced across them."""
    return jax.device_put(ts, sharding_of(ts, mesh, axis))


def sharding_of(ts: TrainState, mesh, axis: str = "batch") -> TrainState:
    """The layout `shard` gives a train state (or its `jax.eval_shape`): a tree of
    `NamedSharding`s, usable as a jit's `out_shardings`."""
    tm = jax.tree_util.tree_map
    replicated = NamedSharding(mesh, PartitionSpec())

    def along(dim):
        return lambda _: NamedSharding(mesh, PartitionSpec(*([None] * dim), axis))

    replay = None
    if ts.replay is not None:
        kept, devices = jax.tree_util.tree_leaves(ts.replay.carry)[0].shape[1], mesh.shape[axis]
        if kept % devices:
            raise ValueError(f"the replay keeps {kept} environments per rollout (train.replay_envs), which cannot be "
                             f"split over {devices} devices: make it a multiple of {devices}")
        replay = replay_lib.Replay(tm(along(2), ts.replay.data), tm(along(1), ts.replay.carry), replicated)
    return TrainState(tm(lambda _: replicated, ts.params), tm(lambda _: replicated, ts.opt_state),
                      tm(along(0), ts.env_state), tm(along(0), ts.agent), replay, replicated, replicated)


NONFINITE = "nonfinite_at"  # `repeated`'s metric: the first of its updates (1-based) with a non-finite metric, 0: none
UPDATES = "updates"  # `repeated`'s metric: how many updates its sums are over


def repeated(update: Callable, layout: Optional[TrainState] = None, loop: bool = True) -> Callable:
    """`updates(ts, n, world=None) -> (ts, sums)`: `n` updates (in `world`, as `update`
    takes it) in one call, a loop on the device (one
    compile serves every n), with each metric summed over them, `UPDATES` (= n) and
    `NONFINITE` (the first update, counted from 1, whose metrics were not all finite;
    0 when all were). The host reads one small dict per call, not one per update.
    `layout` (`sharding_of`) pins the state's sharding on the way in and out, so that the
    state a call returns is laid out as the next call was compiled for. With `loop=False`
    a call runs exactly one update (n must be 1) and no device loop: on this CPU a loop
    around the update runs it at half the speed (docs/benchmarks.md, "Updates per call")."""

    def finite(metrics):
        return jnp.all(jnp.stack([jnp.all(jnp.isfinite(v)) for v in jax.tree_util.tree_leaves(metrics)]))

    def updates(ts: TrainState, n, world=None):
        if not loop:  # one update, the same outputs
            ts, metrics = update(ts, world)
            return ts, {**metrics, UPDATES: jnp.int32(1), NONFINITE: jnp.where(finite(metrics), 0, 1).astype(jnp.int32)}
        _, example = jax.eval_shape(update, ts, world)
        zeros = jax.tree_util.tree_map(lambda m: jnp.zeros(m.shape, m.dtype), example)

        def body(i, carry):
            ts, sums, bad = carry
            ts, metrics = update(ts, world)
            bad = jnp.where((bad == 0) & ~finite(metrics), i + 1, bad)
            return ts, jax.tree_util.tree_map(jnp.add, sums, metrics), bad

        ts, sums, bad = jax.lax.fori_loop(0, n, body, (ts, zeros, jnp.int32(0)))
        return ts, {**sums, UPDATES: jnp.asarray(n, jnp.int32), NONFINITE: bad}

    if layout is None:
        return jax.jit(updates, donate_argnums=0)
    replicated = NamedSharding(jax.tree_util.tree_leaves(layout)[0].mesh, PartitionSpec())
    return jax.jit(updates, donate_argnums=0, in_shardings=(layout, replicated, replicated),
                   out_shardings=(layout, replicated))
