"""Typed configuration: YAML files -> nested frozen dataclasses validated by pydantic, with CLI overrides.

The configuration is a tree of frozen dataclasses rooted at `Config`. Each leaf's
annotation gives its type and, through pydantic's `Field`, its range (`Count`: an int
>= 1, `Fraction`: a float in [0, 1], ...); choices are `Literal`s, list-valued keys are
fixed-length tuples. Types are strict: an int key takes no bool, float or digit string;
a float key takes ints (as floats) but no bool, string, nan or inf; a boolean key takes
only true/false. Adding a section is a matter of writing a `_Section` dataclass and
adding it as a field (with `field(default_factory=...)`) of its parent.

Loading goes file(s) -> dict -> dotted overrides merged into the dict -> one call to
`from_dict`, where pydantic builds and validates the whole tree. Checks involving
several keys are each section's `_cross_checks`, run as a pydantic model validator once
the section's keys are individually valid (so a parent may rely on valid children).
Every problem raises `ConfigError` (a `ValueError`) whose message starts with the full
dotted key; an unknown key comes with the key likely meant. Building a dataclass
directly (`EnvConfig(...)`, `dataclasses.replace`) does not validate; `.validate()` does.

YAML is read with a stricter resolver than PyYAML's default YAML 1.1 one: only
`true`/`false` (any case style) are booleans (so `yes`, `on`, `n` stay strings and are
rejected for boolean keys), and exponent floats without a dot such as `1e-3` are
floats rather than strings. Duplicate keys in a mapping are an error.

Typical use::

    cfg = load_config("configs/default.yaml", ["env.num_envs=32", "env.render.culling=false"])

The command lines read `--config` and `--set` through `a2catvn_jax.cli`. The choice of
pydantic over the alternatives: docs/config.md.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import functools
import os
import re
import types
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import (
    Annotated,
    Any,
    Literal,
    Optional,
    TypeVar,
    Union,
    get_args,
    get_origin,
    get_type_hints,
)

import yaml
from pydantic import (
    BeforeValidator,
    ConfigDict,
    Field,
    Strict,
    TypeAdapter,
    ValidationError,
    model_validator,
)

from a2catvn_jax.errors import UserError

__all__ = [
    "ConfigError",
    "SceneConfig",
    "RenderConfig",
    "EnvConfig",
    "AgentConfig",
    "LossWeights",
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
]


CONFIGS = Path(__file__).resolve().parents[1] / "configs"  # the YAML files of a source checkout


class ConfigError(ValueError, UserError):
    """Invalid configuration: unknown key, wrong type, bad value, bad file or override.

    `key` is the full dotted key the error is about, or None when it concerns a file
    or an override string as a whole.
    """

    def __init__(self, message: str, key: Optional[str] = None):
        super().__init__(message)
        self.key = key


# ----------------------------------------------------------------------- leaf types


def _true_false(value: Any) -> Any:
    """The words true / false (any case; a dict or a caller may hold them as text) as booleans."""
    if isinstance(value, str) and value.strip().lower() in ("true", "false"):
        return value.strip().lower() == "true"
    return value


def _list_as_tuple(value: Any) -> Any:
    return tuple(value) if isinstance(value, list) else value


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
Pair = Annotated[tuple[T, T], Strict(), BeforeValidator(_list_as_tuple)]
Quad = Annotated[tuple[T, T, T, T], Strict(), BeforeValidator(_list_as_tuple)]


def _join(path: str, name: str) -> str:
    """Dotted key of `name` inside the section at `path` ("" is the top level)."""
    return f"{path}.{name}" if path else name


class _CrossCheckFailed(ValueError):
    """Raised by the model validator; `from_dict` asks the section for its messages with full keys."""

    def __init__(self, section: _Section):
        super().__init__(f"{type(section).__name__}: cross-field check failed")
        self.section = section


class _Section:
    """Base of the sections: the pydantic settings and the hooks every section shares."""

    __pydantic_config__ = ConfigDict(extra="forbid", allow_inf_nan=False)

    def _cross_checks(self, k: Callable[[str], str]) -> Iterator[tuple[str, str]]:
        """Yield (full key, message) for each failed check that involves several keys (or
        needs its own message); `k` maps a key of this section to its full dotted key."""
        yield from ()

    @model_validator(mode="before")
    @classmethod
    def _empty_means_defaults(cls, data: Any) -> Any:
        return {} if data is None else data  # `scene:` with nothing under it

    @model_validator(mode="after")
    def _run_cross_checks(self) -> Any:
        if next(self._cross_checks(lambda key: key), None) is not None:
            raise _CrossCheckFailed(self)
        return self

    def validate(self, path: str = "") -> None:
        """Raise `ConfigError` (keys under `path`) unless this section is valid as a whole."""
        from_dict(type(self), to_dict(self), path)


# ----------------------------------------------------------------------- the sections


@dataclass(frozen=True)
class SceneConfig(_Section):
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
        if lo < 1.5:
            yield k("room_size"), f"minimum room side must be >= 1.5 m, got {lo}"
        if lo > hi:
            yield k("room_size"), f"minimum room side {lo} exceeds maximum {hi}"
        if self.kind == "mjcf" and (self.mjcf_path or "").strip() == "":
            yield k("mjcf_path"), f"required when {k('kind')} is 'mjcf'"
        if self.kind != "mjcf" and self.mjcf_path is not None:
            yield k("mjcf_path"), (f"only allowed when {k('kind')} is 'mjcf' (it is {self.kind!r}); "
                                   f"set {k('kind')}=mjcf or remove {k('mjcf_path')}")


@dataclass(frozen=True)
class RenderConfig(_Section):
    """Camera images: resolution, field of view and renderer knobs."""

    image_size: Int = 64  # square images, pixels
    fovy: Annotated[float, Strict(), Field(gt=10, lt=120)] = 60.0  # vertical field of view, degrees
    column_candidates: Count = 24  # per-image-column candidate cap of the culled renderer
    culling: Bool = True
    # raycast: this package's exact ray caster; mjx: MuJoCo's mjx.render (impl warp, package warp-lang);
    # auto: the faster of the two on this device, measured when the environment is built
    backend: Literal["raycast", "mjx", "auto"] = "raycast"

    def _cross_checks(self, k):
        if self.image_size < 16:
            yield k("image_size"), f"{self.image_size} is too small for the network (minimum 16)"
        if self.image_size > 512:
            yield k("image_size"), f"{self.image_size} is too large (maximum 512)"


@dataclass(frozen=True)
class EnvConfig(_Section):
    """The batched navigation environment: agents, goals, episodes, noise, curriculum."""

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
        if self.scene.height <= self.camera_height + 0.1:
            yield k("scene.height"), (f"ceiling height {self.scene.height} must exceed {k('camera_height')} "
                                      f"({self.camera_height}) by more than 0.1 m")
        steepest = self.render.fovy / 2 + self.max_tilt_deg
        if steepest >= 85.0:
            yield k("max_tilt_deg"), (f"{k('render.fovy')} / 2 + {k('max_tilt_deg')} = {steepest:g} degrees "
                                      f"must be < 85 so that camera rays never become vertical")
        if self.goal == "room" and self.scene.kind != "house":
            yield k("goal"), (f"room-type goals need houses with rooms: {k('goal')}='room' requires "
                              f"{k('scene.kind')}='house' (it is {self.scene.kind!r})")


@dataclass(frozen=True)
class AgentConfig(_Section):
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
    blind: Bool = False  # the network sees observation and target images as zeros (a control)
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
class LossWeights(_Section):
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
class TrainConfig(_Section):
    """Batched A2C with off-policy critic and auxiliary tasks; optimiser; run bookkeeping."""

    total_frames: Count = 40_000_000  # f_max: agent steps over all environments
    rollout_length: Count = 20  # l
    gamma: Fraction = 0.99
    learning_rate: Positive = 7e-4
    lr_schedule: Literal["linear", "constant"] = "linear"  # linear: lr * (f_max - f) / f_max
    rmsprop_decay: Fraction = 0.99  # RMSprop alpha
    rmsprop_eps: Positive = 1e-5
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
    keep_checkpoints: Count = 3
    grad_norm_every: Every = 0  # log each loss term's gradient norm on the shared conv layers every N updates (0: off)

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
        # Reward prediction sees 3 frames (networks.RP_FRAMES); its windows lie inside one stored rollout.
        window = 3 + (self.reward_prediction_target == "next_frame")
        if self.loss_weights.reward_prediction > 0 and self.rollout_length < window:
            yield k("rollout_length"), (f"reward prediction ({k('reward_prediction_target')}="
                                        f"{self.reward_prediction_target}) needs windows of {window} steps inside one "
                                        f"rollout: must be >= {window}, got {self.rollout_length}")


@dataclass(frozen=True)
class PretrainConfig(_Section):
    """Supervised pre-training of the conv base with the depth / segmentation heads (paper, Table I)."""

    dataset_size: Count = 200_000  # observations at random poses in the training scenes
    epochs: Count = 30
    batch_size: Count = 64
    learning_rate: Positive = 1e-3  # Adam


@dataclass(frozen=True)
class Config(_Section):
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


# ------------------------------------------------------------------ schema look-ups


@functools.cache
def _adapter(cls: type) -> TypeAdapter:
    return TypeAdapter(cls)


@functools.cache
def _field_types(cls: type) -> dict[str, Any]:
    """Annotations (with their constraints) of the init fields of dataclass `cls`, in field order."""
    hints = get_type_hints(cls, include_extras=True)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if f.init}


def _bare(tp: Any) -> Any:
    """`tp` without `Annotated` constraints and without `Optional`."""
    while True:
        if get_origin(tp) is Annotated:
            tp = get_args(tp)[0]
        elif get_origin(tp) in (Union, types.UnionType) and type(None) in get_args(tp) and len(get_args(tp)) == 2:
            tp = next(a for a in get_args(tp) if a is not type(None))
        else:
            return tp


def _is_section(tp: Any) -> bool:
    tp = _bare(tp)
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _annotation_at(root: type, loc: Sequence[Any]) -> Any:
    """The annotation at pydantic error location `loc` (names, and indices into tuples)."""
    tp: Any = root
    for part in loc:
        tp = _bare(tp)
        if isinstance(part, int) and get_origin(tp) is tuple and part < len(get_args(tp)):
            tp = get_args(tp)[part]
        elif isinstance(part, str) and _is_section(tp):
            tp = _field_types(tp).get(part, Any)
        else:
            return Any
    return tp


def _all_keys(cls: type, path: str = "") -> list[str]:
    """Every dotted key (sections and leaves) of the tree rooted at `cls`."""
    out = []
    for name, tp in _field_types(cls).items():
        key = _join(path, name)
        out.append(key)
        if _is_section(tp):
            out.extend(_all_keys(_bare(tp), key))
    return out


def config_keys(cls: Optional[type] = None) -> list[str]:
    """All dotted leaf keys of the dataclass tree `cls` (default `Config`), in field order."""
    cls = Config if cls is None else cls
    return [k for k in _all_keys(cls) if not _is_section(_annotation_at(cls, k.split(".")))]


# ------------------------------------------------------------------------- messages


def _describe(value: Any) -> str:
    return f"{value!r} ({type(value).__name__})"


def _unknown_key_error(cls: type, name: str, path: str, root: Optional[type]) -> ConfigError:
    """The error for key `name` that section `cls` at `path` lacks, with the likely key meant
    (looked for in the whole tree `root` too, when given)."""
    full = _join(path, name)
    valid = list(_field_types(cls))
    suggestions: list[str] = []
    everywhere = _all_keys(root) if root is not None else []
    # The same name elsewhere in the tree ("env.fovy" -> "env.render.fovy").
    suggestions += [k for k in everywhere if k.rsplit(".", 1)[-1] == name and k != full]
    # A typo of a key in this section.
    suggestions += [_join(path, m) for m in difflib.get_close_matches(name, valid, n=3, cutoff=0.6)]
    if not suggestions and everywhere:
        leaf_names: dict[str, str] = {}
        for k in everywhere:
            leaf_names.setdefault(k.rsplit(".", 1)[-1], k)
        suggestions += [leaf_names[m] for m in difflib.get_close_matches(name, list(leaf_names), n=3, cutoff=0.7)]
    suggestions = list(dict.fromkeys(suggestions))[:3]
    msg = f"unknown key {full!r}"
    if suggestions:
        msg += "; did you mean " + " or ".join(repr(s) for s in suggestions) + "?"
    where = f"in section {path!r}" if path else "at the top level"
    msg += f" Valid keys {where}: " + ", ".join(valid)
    return ConfigError(msg, key=full)


def _section_message(tp: Any, value: Any) -> str:
    keys = ", ".join(_field_types(_bare(tp)))
    return f"is a section; expected a mapping of its keys ({keys}), got {_describe(value)}"


def _list_message(tp: Any, value: Any) -> str:
    """'expected a list of 2 integers, got ...' for the fixed-length tuple annotation `tp`."""
    args = get_args(_bare(tp))
    kinds = {_bare(a) for a in args}
    names = {int: "integers", float: "numbers", bool: "booleans", str: "strings"}
    what = names.get(kinds.pop(), "values") if len(kinds) == 1 else "values"
    if isinstance(value, (list, tuple)):
        return f"expected a list of {len(args)} {what}, got {len(value)} items: {list(value)!r}"
    return f"expected a list of {len(args)} {what}, got {_describe(value)}"


def _number(x: Any) -> str:
    if isinstance(x, int) and x >= 2**16 and x & (x - 1) == 0:
        return f"2**{x.bit_length() - 1}"
    return f"{x:g}" if isinstance(x, float) else str(x)


def _range_message(tp: Any, value: Any) -> str:
    """'must be in [0, 1], got 1.5' from the bounds `Field` put on annotation `tp`."""
    bounds = {}
    for meta in getattr(tp, "__metadata__", ()):
        for constraint in getattr(meta, "metadata", ()):
            for name in ("gt", "ge", "lt", "le"):
                if getattr(constraint, name, None) is not None:
                    bounds[name] = getattr(constraint, name)
    lo = ("[", bounds["ge"]) if "ge" in bounds else ("(", bounds["gt"]) if "gt" in bounds else None
    hi = ("]", bounds["le"]) if "le" in bounds else (")", bounds["lt"]) if "lt" in bounds else None
    if lo and hi:
        return f"must be in {lo[0]}{_number(lo[1])}, {_number(hi[1])}{hi[0]}, got {value!r}"
    if lo:
        return f"must be {'>=' if lo[0] == '[' else '>'} {_number(lo[1])}, got {value!r}"
    if hi:
        return f"must be {'<=' if hi[0] == ']' else '<'} {_number(hi[1])}, got {value!r}"
    return f"out of range, got {value!r}"


_TYPE_MESSAGES = {
    "int_type": "expected an integer",
    "float_type": "expected a number",
    "bool_type": "expected true or false",
    "string_type": "expected a string",
}
_RANGE_ERRORS = {"greater_than", "greater_than_equal", "less_than", "less_than_equal"}
_UNKNOWN_KEY_ERRORS = {"unexpected_keyword_argument", "extra_forbidden", "invalid_key"}


def _key(path: str, loc: Sequence[Any]) -> str:
    key = path
    for part in loc:
        key = f"{key}[{part}]" if isinstance(part, int) else _join(key, str(part))
    return key


def _problems(root: type, path: str, error: ValidationError) -> list[ConfigError]:
    """One `ConfigError` per problem pydantic found validating `root` at `path`: unknown keys
    first, then values of the wrong shape (a list of the wrong length, a section that is not
    a mapping), then the rest."""
    unknown, shapes, others = [], [], []
    for err in error.errors():
        kind, loc, value = err["type"], tuple(err["loc"]), err["input"]
        if kind in _UNKNOWN_KEY_ERRORS:
            section = _bare(_annotation_at(root, loc[:-1]))
            unknown.append(_unknown_key_error(section, str(loc[-1]), _key(path, loc[:-1]), root if not path else None))
            continue
        if kind == "value_error" and isinstance(err.get("ctx", {}).get("error"), _CrossCheckFailed):
            checks = err["ctx"]["error"].section._cross_checks(functools.partial(_join, _key(path, loc)))
            others += [ConfigError(f"{key}: {msg}", key=key) for key, msg in checks]
            continue
        if kind == "missing" and loc and isinstance(loc[-1], int):  # a list shorter than its tuple
            loc = loc[:-1]
        tp, key = _annotation_at(root, loc), _key(path, loc)
        if kind in ("dataclass_type", "dataclass_args_type"):
            shapes.append(ConfigError(f"{key}: {_section_message(tp, value)}", key=key))
            continue
        if kind in ("tuple_type", "too_long", "too_short", "missing") and get_origin(_bare(tp)) is tuple:
            shapes.append(ConfigError(f"{key}: {_list_message(tp, value)}", key=key))
            continue
        if kind in _TYPE_MESSAGES:
            msg = f"{_TYPE_MESSAGES[kind]}, got {_describe(value)}"
        elif kind == "finite_number":
            msg = f"expected a finite number, got {value!r}"
        elif kind == "literal_error":
            msg = f"invalid value {value!r}; allowed values: {err['ctx']['expected']}"
        elif kind in _RANGE_ERRORS:
            msg = _range_message(tp, value)
        else:
            msg = f"{err['msg']}, got {_describe(value)}"
        others.append(ConfigError(f"{key or 'top level'}: {msg}", key=key or None))
    problems = {str(p): p for p in unknown + shapes + others}  # a short list misses several items
    return list(problems.values())


# ------------------------------------------------------------------- dicts and trees


def from_dict(cls: type, data: Optional[Mapping], path: str = "") -> Any:
    """Build and validate an instance of dataclass `cls` from a (possibly partial) mapping.

    Missing keys keep their defaults; sub-sections are built recursively; pydantic checks
    types and ranges, then the cross-field checks. `path` is the dotted key of `cls`
    inside a larger tree, used in messages. Raises `ConfigError` for unknown keys, wrong
    types and invalid values: the first problem found, naming the keys of any others.
    """
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        where = path or "top level"
        raise ConfigError(f"{where}: expected a mapping, got {_describe(data)}", key=path or None)
    try:
        return _adapter(cls).validate_python(dict(data))
    except ValidationError as e:
        problems = _problems(cls, path, e)
    first = problems[0]
    more = list(dict.fromkeys(p.key or "top level" for p in problems[1:] if p.key != first.key))
    if not more:
        raise first from None
    raise ConfigError(f"{first} (also invalid: {', '.join(more)})", key=first.key) from None


def to_dict(instance: Any) -> Any:
    """Plain nested dict of a config dataclass tree (tuples become lists), YAML/JSON ready.

    Structural, so that it also takes a tree built directly, not validated yet."""
    if dataclasses.is_dataclass(instance) and not isinstance(instance, type):
        return {f.name: to_dict(getattr(instance, f.name)) for f in dataclasses.fields(instance)}
    if isinstance(instance, (tuple, list)):
        return [to_dict(v) for v in instance]
    if isinstance(instance, Mapping):
        return {k: to_dict(v) for k, v in instance.items()}
    return instance


# --------------------------------------------------------------------------- YAML I/O

_BOOL_TAG = "tag:yaml.org,2002:bool"
_FLOAT_TAG = "tag:yaml.org,2002:float"
_STRICT_BOOL = re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$")
# Floats with an exponent but no dot ("1e-3", "2E5"), which YAML 1.1 reads as strings.
_EXP_FLOAT = re.compile(r"^[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+$")


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader with YAML 1.2-style booleans, dot-less exponent floats, no duplicate keys."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                dup = key in seen
                seen.add(key)
            except TypeError:
                continue  # unhashable key: let the base class report it
            if dup:
                raise yaml.constructor.ConstructorError(
                    "while constructing a mapping", node.start_mark, f"found duplicate key {key!r}", key_node.start_mark
                )
        return super().construct_mapping(node, deep=deep)


_StrictLoader.yaml_implicit_resolvers = {
    ch: [(tag, rx) for tag, rx in resolvers if tag != _BOOL_TAG]
    for ch, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_StrictLoader.add_implicit_resolver(_BOOL_TAG, _STRICT_BOOL, list("tTfF"))
_StrictLoader.add_implicit_resolver(_FLOAT_TAG, _EXP_FLOAT, list("-+0123456789"))


class _Dumper(yaml.SafeDumper):
    """SafeDumper that also quotes strings `_StrictLoader` would read as floats."""


_Dumper.add_implicit_resolver(_FLOAT_TAG, _EXP_FLOAT, list("-+0123456789"))
# Sections as block mappings, lists (tuples) inline: `grid: [2, 2]`.
_Dumper.add_representer(
    list, lambda dumper, data: dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=True)
)


def _yaml_load(text: str) -> Any:
    return yaml.load(text, Loader=_StrictLoader)


def _read_yaml(path: str | os.PathLike) -> dict:
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {path}") from None
    except OSError as e:
        raise ConfigError(f"cannot read config file {path}: {e}") from None
    try:
        data = _yaml_load(text)
    except yaml.YAMLError as e:
        raise ConfigError(f"invalid YAML in config file {path}: {e}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(
            f"config file {path}: top level must be a mapping of keys and sections, got {type(data).__name__}"
        )
    return data


# -------------------------------------------------------------------------- overrides


def parse_override(text: str) -> tuple[str, str]:
    """Split "a.b.c=value" into ("a.b.c", "value"); `ConfigError` if malformed."""
    if not isinstance(text, str) or "=" not in text:
        raise ConfigError(f"malformed override {text!r}: expected KEY=VALUE, e.g. env.num_envs=8")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key or any(part.strip() == "" or part != part.strip() for part in key.split(".")):
        raise ConfigError(f"malformed override {text!r}: bad key {key!r}, expected a dotted key like env.num_envs")
    return key, raw


def _override_value(raw: str, tp: Any, text: str, key: str) -> Any:
    """YAML-parse an override value; string-typed keys fall back to the raw text."""
    stringy = _bare(tp) is str
    try:
        value = _yaml_load(raw)
    except yaml.YAMLError as e:
        if stringy:
            return raw.strip()
        raise ConfigError(f"{key}: cannot parse value in override {text!r}: {e}", key=key) from None
    if stringy and value is not None and not isinstance(value, str):
        return raw.strip()
    return value


def _apply_override(data: dict, text: str, root: type) -> None:
    key, raw = parse_override(text)
    parts = key.split(".")
    cls, node, path = root, data, ""
    for i, name in enumerate(parts):
        hints = _field_types(cls)
        if name not in hints:
            raise _unknown_key_error(cls, name, path, root)
        full = _join(path, name)
        tp = hints[name]
        last = i == len(parts) - 1
        if _is_section(tp):
            if last:
                leaves = ", ".join(_join(full, k) for k in _field_types(_bare(tp)))
                raise ConfigError(
                    f"{full}: is a section, not a value; override one of its keys instead ({leaves})", key=full
                )
            child = node.get(name)
            if child is None:
                child = node[name] = {}
            elif not isinstance(child, dict):
                raise ConfigError(f"{full}: is a section; expected a mapping, got {_describe(child)}", key=full)
            cls, node, path = _bare(tp), child, full
        else:
            if not last:
                raise ConfigError(f"{full}: is a value, not a section, so {key!r} does not exist", key=full)
            node[name] = _override_value(raw, tp, text, full)


def apply_overrides(cfg: Any, overrides: Sequence[str] = ()) -> Any:
    """Return a re-validated copy of config tree `cfg` with dotted "key=value" overrides applied."""
    data = to_dict(cfg)
    root = type(cfg)
    for text in overrides:
        _apply_override(data, text, root)
    return from_dict(root, data)


def _merge(base: dict, update: Mapping) -> dict:
    """`base` with the keys of `update` set in it, sections (mappings) merged key by key."""
    for key, value in update.items():
        if isinstance(value, Mapping) and isinstance(base.get(key), dict):
            _merge(base[key], value)
        else:
            base[key] = copy.deepcopy(value)
    return base


def load_config(
    path: Optional[str | os.PathLike | Sequence[str | os.PathLike]] = None, overrides: Sequence[str] = (), *,
    schema: type = Config
) -> Any:
    """Load a config: defaults <- YAML file(s) at `path` (each may be partial; None: none) <- overrides.

    `path` is one file or a list of files; a later file's keys override an earlier
    one's (sections merge key by key, a list is replaced whole). Overrides are
    "dotted.key=value" strings; the value is parsed as YAML (numbers, `true`/`false`,
    `null`, `[1, 2]` lists), except that string-typed keys take the raw text when it
    does not parse to a string. The merged result is validated once. `schema` is the
    root dataclass (default `Config`).
    """
    if isinstance(overrides, str):
        overrides = [overrides]
    paths = [] if path is None else [path] if isinstance(path, (str, os.PathLike)) else list(path)
    data: dict = {}
    for one in paths:
        _merge(data, _read_yaml(one))
    for text in overrides:
        _apply_override(data, text, schema)
    return from_dict(schema, data)


def save_config(cfg: Any, path: str | os.PathLike) -> None:
    """Write `cfg` as YAML (every key) so that `load_config(path)` gives an equal config."""
    path = os.fspath(path)
    parent = os.path.dirname(path)
    if parent:
        os.makedirs(parent, exist_ok=True)
    text = yaml.dump(to_dict(cfg), Dumper=_Dumper, sort_keys=False, default_flow_style=False)
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("# a2catvn_jax configuration (written by save_config)\n")
        fh.write(text)
