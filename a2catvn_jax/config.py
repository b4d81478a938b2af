"""The configuration schema: nested frozen dataclasses validated by pydantic, rooted at `Config`.

Each leaf's annotation gives its type and, through pydantic's `Field`, its range
(`Count`: an int >= 1, `Fraction`: a float in [0, 1], ...); choices are `Literal`s,
list-valued keys are fixed-length tuples. Types are strict: an int key takes no bool,
float or digit string; a float key takes ints (as floats) but no bool, string, nan or
inf; a boolean key takes only true/false. Adding a section is a matter of writing a
`Section` dataclass and adding it as a field (with `field(default_factory=...)`) of its
parent; checks involving several keys are the section's `_cross_checks`. Building a
dataclass directly (`EnvConfig(...)`, `dataclasses.replace`) does not validate;
`.validate()` does. Constants that the schema checks and other layers use
(`MIN_IMAGE_SIZE`, `RP_FRAMES`) are defined here, in the bottom layer.

Reading YAML files and overrides, `from_dict` / `to_dict` and the `ConfigError`
messages are the schema-free `a2catvn_jax.configio`; this module binds `Config` as
their default root. Typical use::

    cfg = load_config("configs/default.yaml", ["env.num_envs=32", "env.render.culling=false"])

The command lines read `--config` and `--set` through `a2catvn_jax.cli`. The choice of
pydantic over the alternatives: docs/config.md.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, Optional, TypeVar

from pydantic import BeforeValidator, Field, Strict

from a2catvn_jax import configio
from a2catvn_jax.configio import (  # noqa: F401  (Section: the sections' base; the rest re-exported)
    ConfigError,
    Section,
    apply_overrides,
    from_dict,
    parse_override,
    save_config,
    to_dict,
)

__all__ = [
    "ConfigError",
    "SceneConfig",
    "RenderConfig",
    "EnvConfig",
    "AgentConfig",
    "LossWeights",
    "EvalConfig",
    "TrainConfig",
    "PretrainConfig",
    "Config",
    "from_dict",
    "to_dict",
    "config_keys",
    "load_config",
    "apply_overrides",
    "parse_override",
    "save_config",
    "MIN_IMAGE_SIZE",
    "MIN_ROOM_SIDE",
    "RP_FRAMES",
    "HOUSES",
    "AGENT_POLICIES",
]


CONFIGS = Path(__file__).resolve().parents[1] / "configs"  # the YAML files of a source checkout
MIN_IMAGE_SIZE = 16  # smallest env.render.image_size the network takes
RP_FRAMES = 3  # consecutive frames seen by the reward-prediction head (agent.networks)
MIN_ROOM_SIDE = 1.5  # metres: the smallest room side a generated house may have (env.scene.room_size)
BODY_MARGIN = 0.1  # metres: the agent's body reaches this far above its camera (env.world)
HOUSES = ("train", "held-out", "new-targets")  # the house sets an agent is evaluated in (run.restore)
AGENT_POLICIES = ("sample", "greedy")  # how a trained agent acts in evaluation: sampled or argmax actions


# ----------------------------------------------------------------------- leaf types


def _true_false(value: Any) -> Any:
    """The words true / false (any case; a dict or a caller may hold them as text) as booleans."""
    if isinstance(value, str) and value.strip().lower() in ("true", "false"):
        return value.strip().lower() == "true"
    return value


def _list_as_tuple(value: Any) -> Any:
    return tuple(value) if isinstance(value, list) else value


def _one_or_list(value: Any) -> Any:
    return (value,) if isinstance(value, str) else _list_as_tuple(value)


T = TypeVar("T")
Int = Annotated[int, Strict()]
Float = Annotated[float, Strict()]  # strict still takes an int (as a float)
Bool = Annotated[bool, Strict(), BeforeValidator(_true_false)]
Str = Annotated[str, Strict()]
Count = Annotated[int, Strict(), Field(ge=1)]
Seed = Annotated[int, Strict(), Field(ge=0, lt=2**31)]
Positive = Annotated[float, Strict(), Field(gt=0)]
NonNegative = Annotated[float, Strict(), Field(ge=0)]
Every = Annotated[int, Strict(), Field(ge=0)]  # a period in updates; 0: never
Fraction = Annotated[float, Strict(), Field(ge=0, le=1)]
# Lists (YAML's sequences) of a fixed length; nothing else (no string, set or scalar).
BLIND_MODES = ("none", "both", "target", "observation")


def _blind_mode(value: Any) -> Any:
    """`agent.blind`'s earlier yes / no: true (YAML or --set) is "both", false is "none"."""
    if isinstance(value, bool):
        return "both" if value else "none"
    return {"true": "both", "false": "none"}.get(value, value) if isinstance(value, str) else value


Blind = Annotated[Literal[BLIND_MODES], BeforeValidator(_blind_mode)]
Pair = Annotated[tuple[T, T], Strict(), BeforeValidator(_list_as_tuple)]
Quad = Annotated[tuple[T, T, T, T], Strict(), BeforeValidator(_list_as_tuple)]
# A list of one or more choices (a single choice may be written alone).
Choices = Annotated[tuple[T, ...], Strict(), BeforeValidator(_one_or_list), Field(min_length=1)]


# ----------------------------------------------------------------------- the sections


@dataclass(frozen=True)
class SceneConfig(Section):
    """Which scenes (houses, rooms, mazes or a user MJCF file) the batch is built from."""

    kind: Literal["house", "room", "maze", "mjcf"] = "house"
    num_scenes: Count = 4  # distinct scenes in the batch
    seed: Seed = 0  # scene generation seed
    grid: Pair[Int] = (2, 2)  # house room grid (rows, cols); maze cells
    room_size: Pair[Float] = (3.0, 4.5)  # min/max room side, metres
    height: Positive = 2.6  # ceiling height, metres
    mjcf_path: Optional[Str] = None  # MJCF file, only (and always) with kind "mjcf"

    def _cross_checks(self, k):
        if min(self.grid) < 1:
            yield k("grid"), f"both entries must be >= 1, got {list(self.grid)}"
        lo, hi = self.room_size
        if lo < MIN_ROOM_SIDE:
            yield k("room_size"), f"minimum room side must be >= {MIN_ROOM_SIDE} m, got {lo}"
        if lo > hi:
            yield k("room_size"), f"minimum room side {lo} exceeds maximum {hi}"
        if self.kind == "mjcf" and (self.mjcf_path or "").strip() == "":
            yield k("mjcf_path"), f"required when {k('kind')} is 'mjcf'"
        if self.kind != "mjcf" and self.mjcf_path is not None:
            yield k("mjcf_path"), (f"only allowed when {k('kind')} is 'mjcf' (it is {self.kind!r}); "
                                   f"set {k('kind')}=mjcf or remove {k('mjcf_path')}")


@dataclass(frozen=True)
class RenderConfig(Section):
    """Camera images: resolution, field of view and renderer knobs."""

    image_size: Int = 64  # square images, pixels
    fovy: Annotated[float, Strict(), Field(gt=10, lt=120)] = 60.0  # vertical field of view, degrees
    column_candidates: Count = 24  # per-image-column candidate cap of the culled renderer
    culling: Bool = True
    # raycast: this package's exact ray caster; mjx: MuJoCo's mjx.render (impl warp, package warp-lang);
    # auto: the faster of the two on this device, measured when the environment is built
    backend: Literal["raycast", "mjx", "auto"] = "raycast"

    def _cross_checks(self, k):
        if self.image_size < MIN_IMAGE_SIZE:
            yield k("image_size"), f"{self.image_size} is too small for the network (minimum {MIN_IMAGE_SIZE})"
        if self.image_size > 512:
            yield k("image_size"), f"{self.image_size} is too large (maximum 512)"


@dataclass(frozen=True)
class EnvConfig(Section):
    """The batched navigation environment: agents, goals, episodes, noise, curriculum."""

    kind: Literal["mujoco", "synthetic"] = "mujoco"  # the MuJoCo world of houses, or a rendering-free test bench (env/synthetic.py)
    num_envs: Count = 16  # B
    new_scene_per_episode: Bool = False  # each episode in a scene drawn uniformly (else agent b stays in scene b mod S)
    action_set: Literal["full", "no_tilt", "grid"] = "full"
    goal: Literal["image", "room", "object"] = "image"
    goals_per_scene: Count = 8
    max_episode_steps: Count = 900
    success_distance: Positive = 0.5  # metres (image goals)
    success_heading_deg: Annotated[float, Strict(), Field(gt=0, le=180)] = 45.0  # image goals: heading within this of the target's
    object_distance: Positive = 1.5  # metres (object goals)
    view_fraction: Annotated[float, Strict(), Field(ge=0, lt=1)] = 0.045  # room/object goals: image share showing the goal; 0: not needed
    view_steps: Count = 2  # ... in this many observations in a row
    stop_action: Bool = False  # a "stop" action: success only where the agent stops with the goal reached; a stop elsewhere ends the episode unrewarded
    agent_radius: Annotated[float, Strict(), Field(gt=0, lt=1)] = 0.2  # metres
    camera_height: Positive = 1.0  # metres
    grid_resolution: Annotated[float, Strict(), Field(gt=0, le=1)] = 0.1  # occupancy grid cell size, metres
    complexity: Fraction = 1.0  # curriculum tau
    position_noise: NonNegative = 0.02  # std, metres
    heading_noise_deg: NonNegative = 2.0  # std, degrees
    max_tilt_deg: Annotated[float, Strict(), Field(ge=0, le=60)] = 30.0  # camera tilt bound, degrees
    scene: SceneConfig = field(default_factory=SceneConfig)
    render: RenderConfig = field(default_factory=RenderConfig)

    def _cross_checks(self, k):
        if self.scene.height <= self.camera_height + BODY_MARGIN:
            yield k("scene.height"), (f"ceiling height {self.scene.height} must exceed {k('camera_height')} "
                                      f"({self.camera_height}) by more than {BODY_MARGIN} m")
        steepest = self.render.fovy / 2 + self.max_tilt_deg
        if steepest >= 85.0:
            yield k("max_tilt_deg"), (f"{k('render.fovy')} / 2 + {k('max_tilt_deg')} = {steepest:g} degrees "
                                      f"must be < 85 so that camera rays never become vertical")
        if self.stop_action and self.kind == "synthetic":
            yield k("stop_action"), (f"the synthetic test bench has no stop action: {k('stop_action')}=true needs "
                                     f"{k('kind')}='mujoco'")
        if self.goal == "room" and self.scene.kind != "house":
            yield k("goal"), (f"room-type goals need houses with rooms: {k('goal')}='room' requires "
                              f"{k('scene.kind')}='house' (it is {self.scene.kind!r})")


@dataclass(frozen=True)
class AgentConfig(Section):
    """The network: conv base (shared observation/target stream), memory, heads."""

    memory: Literal["lstm", "frame_stack"] = "lstm"  # LSTM, or the last `stack` frames and a dense layer
    stack: Annotated[int, Strict(), Field(ge=2)] = 4  # frames of the frame-stack variant
    conv_channels: Quad[Int] = (16, 32, 32, 32)  # conv1, conv2 (shared stream), conv3, conv4
    conv_kernels: Quad[Count] = (8, 4, 3, 3)  # square kernel sides of conv1..conv4, each >= its stride
    conv_strides: Quad[Count] = (4, 2, 1, 1)  # strides of conv1..conv4
    conv_padding: Literal["same", "valid"] = "same"  # same: ceil(n / stride) outputs; valid: no padding
    dense_size: Count = 256  # the dense layer after the conv base
    core_size: Count = 256  # LSTM cells (or the frame-stack dense layer)
    segmentation_loss: Literal["mse_rgb", "cross_entropy"] = "mse_rgb"  # class colours (paper) or class ids
    space_to_depth: Bool = False  # run conv1 as a conv on stride x stride pixel blocks (the same function)
    conv_impl: Literal["auto", "xla", "matmul"] = "auto"  # XLA's conv or matrix products (the same function; auto: per layer, the faster on the CPU)
    blind: Blind = "none"  # controls: images of zeros for both, the target only or the observation only (true: both)
    vision_heads: Literal["upsample", "transposed"] = "upsample"  # depth / segmentation head layout
    init: Literal["lecun", "uniform_fan_in"] = "lecun"  # weight initialisation

    def conv_sizes(self, image_size: int) -> list[int]:
        """Side of the image and of conv1..conv4's maps; with valid padding a layer whose
        input is smaller than its kernel ends the list (check `_image_checks`)."""
        sizes = [image_size]
        for kernel, stride in zip(self.conv_kernels, self.conv_strides):
            n = sizes[-1]
            if self.conv_padding == "same":
                sizes.append(-(-n // stride))
            elif n >= kernel:
                sizes.append((n - kernel) // stride + 1)
            else:
                break
        return sizes

    def _cross_checks(self, k):
        if min(self.conv_channels) < 1:
            yield k("conv_channels"), f"all must be >= 1, got {list(self.conv_channels)}"
        for i, (kernel, stride) in enumerate(zip(self.conv_kernels, self.conv_strides)):
            if kernel < stride:
                yield k("conv_kernels"), (f"conv{i + 1}'s kernel {kernel} is smaller than its stride {stride} "
                                          f"({k('conv_strides')}), so its windows would skip pixels")
        if self.space_to_depth and self.conv_kernels[0] % self.conv_strides[0]:
            yield k("space_to_depth"), (f"needs conv1's kernel to be a multiple of its stride, got kernel "
                                        f"{self.conv_kernels[0]} ({k('conv_kernels')}) and stride "
                                        f"{self.conv_strides[0]} ({k('conv_strides')})")

    def _image_checks(self, k, image_size: int, aux_downsize: int, image_key: str, aux_key: str):
        """Checks of the conv stack against the image size and the auxiliary targets'
        resolution (keys of other sections given in full)."""
        sizes = self.conv_sizes(image_size)
        if len(sizes) < 5:
            i = len(sizes)  # the conv layer whose input is smaller than its kernel
            need = 1
            for kernel, stride in zip(self.conv_kernels[::-1], self.conv_strides[::-1]):
                need = (need - 1) * stride + kernel
            kernel, stride = self.conv_kernels[i - 1], self.conv_strides[i - 1]
            yield image_key, (f"{image_size} is too small for the conv stack with {k('conv_padding')}=valid: "
                              f"conv{i} ({kernel}x{kernel}/{stride}) gets {sizes[-1]}x{sizes[-1]} maps (sizes "
                              f"{' -> '.join(map(str, sizes))}); use images of at least {need} pixels or "
                              f"{k('conv_padding')}=same")
        scale = 1
        for stride in self.conv_strides:
            scale *= stride
        if self.vision_heads == "transposed" and scale != 4 * aux_downsize:
            yield k("vision_heads"), (f"'transposed' (two stride-2 transposed convs) brings conv4's maps from "
                                      f"stride {scale} in the image ({k('conv_strides')} {list(self.conv_strides)}) "
                                      f"to stride {scale / 4:g}, which must equal {aux_key} ({aux_downsize})")


@dataclass(frozen=True)
class LossWeights(Section):
    """Weight of each loss term (paper, Table I). A weight of 0 removes the term's computation."""

    actor: NonNegative = 1.0
    critic: NonNegative = 0.5
    entropy: NonNegative = 0.001
    off_policy_critic: NonNegative = 1.0
    pixel_control: NonNegative = 0.05
    reward_prediction: NonNegative = 1.0
    depth: NonNegative = 0.1
    segmentation: NonNegative = 0.1  # observation segmentation
    target_segmentation: NonNegative = 0.1


@dataclass(frozen=True)
class EvalConfig(Section):
    """Evaluation during training: every `every` updates the agent's parameters of that
    moment act in each house set with each policy, at complexity 1, for `episodes`
    episodes drawn with `seed` (the same episodes each time), as `evaluate` would act
    from a checkpoint of that update. Rows go to eval.jsonl / eval.csv / TensorBoard."""

    every: Every = 0  # updates between evaluations (0: none)
    episodes: Count = 100  # per house set and policy
    houses: Choices[Literal[HOUSES]] = ("held-out",)
    policies: Choices[Literal[AGENT_POLICIES]] = ("sample",)
    seed: Seed = 1000  # evaluation episodes' seed

    def _cross_checks(self, k):
        for name in ("houses", "policies"):
            values = getattr(self, name)
            if len(set(values)) < len(values):
                yield k(name), f"lists a value twice: {list(values)}"


@dataclass(frozen=True)
class TrainConfig(Section):
    """Batched A2C with off-policy critic and auxiliary tasks; optimiser; run bookkeeping."""

    total_frames: Count = 40_000_000  # f_max: agent steps over all environments
    rollout_length: Count = 20  # l
    gamma: Fraction = 0.99
    learning_rate: Positive = 7e-4
    lr_schedule: Literal["linear", "constant"] = "linear"  # linear: lr * (f_max - f) / f_max
    lr_scaling: Literal["none", "linear", "sqrt"] = "none"  # learning_rate times b / 16 or sqrt(b / 16) (b: env.num_envs / minibatches, the environments of one gradient step)
    minibatches: Count = 1  # gradient steps per rollout, each on 1 / minibatches of the environments (every minibatches-th one); 1: the paper's one step
    lr_warmup_frames: Annotated[int, Strict(), Field(ge=0)] = 0  # the learning rate rises linearly from 0 over these frames, then follows lr_schedule
    optimizer: Literal["rmsprop", "adam", "lamb"] = "rmsprop"  # after the clip: RMSprop (paper), Adam or LAMB
    rmsprop_decay: Fraction = 0.99  # RMSprop alpha
    rmsprop_eps: Positive = 1e-5  # the optimiser's epsilon (RMSprop's outside the square root; Adam's and LAMB's too)
    max_grad_norm: Positive = 0.5
    replay_size: Int = 2000  # replay buffer, steps per kept environment (whole rollouts are kept)
    replay_envs: Count = 256  # environments kept per rollout (a new block each time): replay_size * min(B, this) steps
    replay_batch: Count = 16  # replay sequences per update (off-policy critic, pixel control, reward prediction)
    pixel_control_gamma: Fraction = 0.9
    pixel_control_cell: Count = 4
    pixel_control_reward: Literal["luminance", "rgb"] = "luminance"  # pseudo-reward: change of luminance or of R, G, B
    reward_prediction_loss: Literal["softmax", "sigmoid"] = "softmax"  # softmax CE (paper) or per-class sigmoid BCE
    reward_prediction_zero_fraction: Fraction = 0.5  # expected share of reward windows that end with zero reward
    reward_prediction_target: Literal["last_frame", "next_frame"] = "last_frame"  # the step whose reward is predicted
    replay_warmup: Bool = False  # fill the replay buffer before the first update (those frames are not counted)
    aux_downsize: Count = 4  # depth / segmentation targets are downsized by this factor
    aux_every: Count = 1  # depth / segmentation losses on every k-th frame of the rollout (1: all, the paper's)
    remat_vision_heads: Bool = False  # recompute the depth / segmentation heads in the backward pass (less memory, same gradients)
    timeout_bootstrap: Bool = True  # a time-out bootstraps the returns from the critic; false: terminal (paper)
    loss_weights: LossWeights = field(default_factory=LossWeights)
    curriculum: Bool = False  # complexity tau rises linearly between two frame counts (paper)
    curriculum_complexity: Pair[Float] = (0.3, 1.0)  # tau before the first and after the second
    curriculum_frames: Pair[Int] = (5_000_000, 10_000_000)
    log_every: Count = 10  # updates between log lines
    checkpoint_every: Count = 500  # updates between checkpoints (and one on exit)
    updates_per_call: Every = 0  # updates one call runs in a device loop (0: 1 on the CPU, log_every on an accelerator)
    keep_checkpoints: Count = 3
    grad_norm_every: Every = 0  # log each loss term's gradient norm on the shared conv layers every N updates (0: off)
    new_houses_every: Every = 0  # updates between replacing the training scenes with as many newly generated ones (0: never)
    eval: EvalConfig = field(default_factory=EvalConfig)  # evaluation during training (off by default)

    def _cross_checks(self, k):
        if self.grad_norm_every % self.log_every:
            yield k("grad_norm_every"), (f"must be a multiple of {k('log_every')} ({self.log_every}): the norms are "
                                         f"written with the log rows, got {self.grad_norm_every}")
        lo, hi = self.curriculum_complexity
        if not (0 <= lo <= 1 and 0 <= hi <= 1):
            yield k("curriculum_complexity"), f"both must be in [0, 1], got {[lo, hi]}"
        f0, f1 = self.curriculum_frames
        if not 0 <= f0 <= f1:
            yield k("curriculum_frames"), f"need 0 <= start <= end, got {[f0, f1]}"
        if self.replay_size < self.rollout_length:
            yield k("replay_size"), (f"must hold at least one rollout ({k('rollout_length')} = "
                                     f"{self.rollout_length}), got {self.replay_size}")
        # Reward prediction sees RP_FRAMES frames; its windows lie inside one stored rollout.
        window = RP_FRAMES + (self.reward_prediction_target == "next_frame")
        if self.loss_weights.reward_prediction > 0 and self.rollout_length < window:
            yield k("rollout_length"), (f"reward prediction ({k('reward_prediction_target')}="
                                        f"{self.reward_prediction_target}) needs windows of {window} steps inside one "
                                        f"rollout: must be >= {window}, got {self.rollout_length}")


@dataclass(frozen=True)
class PretrainConfig(Section):
    """Supervised pre-training of the conv base with the depth / segmentation heads (paper, Table I)."""

    dataset_size: Count = 200_000  # observations at random poses in the training scenes
    epochs: Count = 30
    batch_size: Count = 64
    learning_rate: Positive = 1e-3  # Adam


@dataclass(frozen=True)
class Config(Section):
    """Root of the configuration tree."""

    seed: Seed = 0  # master PRNG seed
    env: EnvConfig = field(default_factory=EnvConfig)
    agent: AgentConfig = field(default_factory=AgentConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    pretrain: PretrainConfig = field(default_factory=PretrainConfig)

    def _cross_checks(self, k):
        size = self.env.render.image_size
        for name in ("pixel_control_cell", "aux_downsize"):
            factor = getattr(self.train, name)
            if size // factor < 2:
                yield k(f"train.{name}"), (f"{factor} leaves fewer than 2 cells across a {size}-pixel image "
                                           f"({k('env.render.image_size')})")
        yield from self.agent._image_checks(lambda key: k(f"agent.{key}"), size, self.train.aux_downsize,
                                            k("env.render.image_size"), k("train.aux_downsize"))
        if self.train.eval.every and self.env.kind != "mujoco":
            yield k("train.eval.every"), (f"evaluation during training needs the MuJoCo world of houses; "
                                          f"{k('env.kind')} is {self.env.kind!r}")
        elif self.train.eval.every and "held-out" in self.train.eval.houses and self.env.scene.kind == "mjcf":
            yield k("train.eval.houses"), (f"held-out houses need generated scenes; {k('env.scene.kind')} is 'mjcf' "
                                           f"(one fixed file)")
        if self.train.new_houses_every and (self.env.kind != "mujoco" or self.env.scene.kind == "mjcf"):
            yield k("train.new_houses_every"), (
                f"new houses need generated scenes; {k('env.kind')} is {self.env.kind!r}" if self.env.kind != "mujoco"
                else f"new houses need generated scenes; {k('env.scene.kind')} is 'mjcf' (one fixed file)")
        elif self.train.new_houses_every and self.env.render.backend == "mjx":
            yield k("train.new_houses_every"), (f"new houses are rendered by the ray caster; {k('env.render.backend')} "
                                                f"is 'mjx', whose render context holds the first houses' models")
        if self.env.num_envs % self.train.minibatches:
            yield k("train.minibatches"), (f"{self.train.minibatches} does not divide {k('env.num_envs')} = "
                                           f"{self.env.num_envs}: each gradient step takes an equal share")



# ------------------------------------------------------------- loading, bound to Config


def config_keys(cls: Optional[type] = None) -> list[str]:
    """All dotted leaf keys of the dataclass tree `cls` (default `Config`), in field order."""
    return configio.config_keys(Config if cls is None else cls)


def load_config(
    path: Optional[str | os.PathLike | Sequence[str | os.PathLike]] = None, overrides: Sequence[str] = (), *,
    schema: type = Config
) -> Any:
    """`configio.load_config` with `Config` as the default root: defaults <- YAML file(s)
    at `path` (later files override earlier ones) <- "dotted.key=value" overrides."""
    return configio.load_config(path, overrides, schema=schema)
