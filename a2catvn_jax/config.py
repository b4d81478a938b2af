"""Typed configuration: YAML files -> nested frozen dataclasses, with CLI overrides.

The configuration is a tree of frozen dataclasses rooted at `Config`. Each section is
a dataclass; each leaf is a plain value whose annotation (`int`, `float`, `bool`,
`str`, `Optional[X]`, `tuple[...]`, `Literal[...]`) drives coercion and type checks.
Adding a section is a matter of writing a dataclass and adding it as a field (with
`field(default_factory=...)`) of its parent.

Loading goes file -> dict -> dotted overrides merged into the dict -> one call to
`from_dict`, which builds and validates the whole tree once. Every problem raises
`ConfigError` (a `ValueError`) whose message starts with the full dotted key.

Typical use::

    cfg = load_config("configs/default.yaml", ["env.num_envs=32", "env.render.culling=false"])

The command lines read `--config` and `--set` through `a2catvn_jax.cli`.

Value checks live in each dataclass's `validate(self, path)` method, called by
`from_dict` right after the section is built (sub-sections are validated before their
parent, so a parent may rely on its children being individually valid).

YAML is read with a stricter resolver than PyYAML's default YAML 1.1 one: only
`true`/`false` (any case style) are booleans (so `yes`, `on`, `n` stay strings and are
rejected for boolean keys), and exponent floats without a dot such as `1e-3` are
floats rather than strings. Duplicate keys in a mapping are an error.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import functools
import math
import numbers
import os
import re
import types
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Optional, Union, get_args, get_origin, get_type_hints

import yaml

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


# --------------------------------------------------------------------------- helpers


def _join(path: str, name: str) -> str:
    """Dotted key of `name` inside the section at `path` ("" is the top level)."""
    return f"{path}.{name}" if path else name


def _check(cond: bool, key: str, msg: str) -> None:
    """Raise `ConfigError("<key>: <msg>")` unless `cond` holds."""
    if not cond:
        raise ConfigError(f"{key}: {msg}", key=key)


def _describe(value: Any) -> str:
    return f"{value!r} ({type(value).__name__})"


# ----------------------------------------------------------------------- the sections


@dataclass(frozen=True)
class SceneConfig:
    """Which scenes (houses, rooms, mazes or a user MJCF file) the batch is built from."""

    kind: Literal["house", "room", "maze", "mjcf"] = "house"
    num_scenes: int = 4  # distinct scenes in the batch
    seed: int = 0  # scene generation seed
    grid: tuple[int, int] = (2, 2)  # house room grid (rows, cols); maze cells
    room_size: tuple[float, float] = (3.0, 4.5)  # min/max room side, metres
    height: float = 2.6  # ceiling height, metres
    mjcf_path: Optional[str] = None  # MJCF file, only (and always) with kind "mjcf"

    def validate(self, path: str = "") -> None:
        k = functools.partial(_join, path)
        _check(self.num_scenes >= 1, k("num_scenes"), f"must be >= 1, got {self.num_scenes}")
        _check(0 <= self.seed < 2**31, k("seed"), f"must be in [0, 2**31), got {self.seed}")
        _check(all(g >= 1 for g in self.grid), k("grid"), f"both entries must be >= 1, got {list(self.grid)}")
        lo, hi = self.room_size
        _check(lo >= 1.5, k("room_size"), f"minimum room side must be >= 1.5 m, got {lo}")
        _check(lo <= hi, k("room_size"), f"minimum room side {lo} exceeds maximum {hi}")
        _check(self.height > 0, k("height"), f"must be > 0, got {self.height}")
        if self.kind == "mjcf":
            _check(
                self.mjcf_path is not None and self.mjcf_path.strip() != "",
                k("mjcf_path"),
                f"required when {k('kind')} is 'mjcf'",
            )
        else:
            _check(
                self.mjcf_path is None,
                k("mjcf_path"),
                f"only allowed when {k('kind')} is 'mjcf' (it is {self.kind!r}); "
                f"set {k('kind')}=mjcf or remove {k('mjcf_path')}",
            )


@dataclass(frozen=True)
class RenderConfig:
    """Camera images: resolution, field of view and renderer knobs."""

    image_size: int = 64  # square images, pixels
    fovy: float = 60.0  # vertical field of view, degrees
    column_candidates: int = 24  # per-image-column candidate cap of the culled renderer
    culling: bool = True

    def validate(self, path: str = "") -> None:
        k = functools.partial(_join, path)
        _check(
            self.image_size >= 16,
            k("image_size"),
            f"{self.image_size} is too small for the network (minimum 16)",
        )
        _check(self.image_size <= 512, k("image_size"), f"{self.image_size} is too large (maximum 512)")
        _check(10.0 < self.fovy < 120.0, k("fovy"), f"must be in (10, 120) degrees, got {self.fovy}")
        _check(self.column_candidates >= 1, k("column_candidates"), f"must be >= 1, got {self.column_candidates}")


@dataclass(frozen=True)
class EnvConfig:
    """The batched navigation environment: agents, goals, episodes, noise, curriculum."""

    num_envs: int = 16  # B
    action_set: Literal["full", "no_tilt", "grid"] = "full"
    goal: Literal["image", "room", "object"] = "image"
    goals_per_scene: int = 8
    max_episode_steps: int = 900
    success_distance: float = 0.5  # metres (image and room goals)
    object_distance: float = 1.0  # metres (object goals)
    agent_radius: float = 0.2  # metres
    camera_height: float = 1.0  # metres
    grid_resolution: float = 0.1  # occupancy grid cell size, metres
    complexity: float = 1.0  # curriculum tau
    position_noise: float = 0.02  # std, metres
    heading_noise_deg: float = 2.0  # std, degrees
    max_tilt_deg: float = 30.0  # camera tilt bound, degrees (tilt actions clamp to it)
    scene: SceneConfig = field(default_factory=SceneConfig)
    render: RenderConfig = field(default_factory=RenderConfig)

    def validate(self, path: str = "") -> None:
        k = functools.partial(_join, path)
        for name in ("num_envs", "goals_per_scene", "max_episode_steps"):
            v = getattr(self, name)
            _check(v >= 1, k(name), f"must be >= 1, got {v}")
        for name in ("success_distance", "object_distance", "camera_height"):
            v = getattr(self, name)
            _check(v > 0, k(name), f"must be > 0, got {v}")
        _check(0 < self.agent_radius < 1, k("agent_radius"), f"must be in (0, 1) metres, got {self.agent_radius}")
        _check(
            0 < self.grid_resolution <= 1,
            k("grid_resolution"),
            f"must be in (0, 1] metres, got {self.grid_resolution}",
        )
        _check(0 <= self.complexity <= 1, k("complexity"), f"must be in [0, 1], got {self.complexity}")
        for name in ("position_noise", "heading_noise_deg"):
            v = getattr(self, name)
            _check(v >= 0, k(name), f"must be >= 0, got {v}")
        _check(0 <= self.max_tilt_deg <= 60, k("max_tilt_deg"), f"must be in [0, 60] degrees, got {self.max_tilt_deg}")

        # Cross-field checks.
        _check(
            self.scene.height > self.camera_height + 0.1,
            k("scene.height"),
            f"ceiling height {self.scene.height} must exceed {k('camera_height')} "
            f"({self.camera_height}) by more than 0.1 m",
        )
        steepest = self.render.fovy / 2 + self.max_tilt_deg
        _check(
            steepest < 85.0,
            k("max_tilt_deg"),
            f"{k('render.fovy')} / 2 + {k('max_tilt_deg')} = {steepest:g} degrees must be < 85 "
            f"so that camera rays never become vertical",
        )
        _check(
            self.goal != "room" or self.scene.kind == "house",
            k("goal"),
            f"room-type goals need houses with rooms: {k('goal')}='room' requires "
            f"{k('scene.kind')}='house' (it is {self.scene.kind!r})",
        )


@dataclass(frozen=True)
class AgentConfig:
    """The network: conv base (shared observation/target stream), memory, heads."""

    memory: Literal["lstm", "frame_stack"] = "lstm"  # LSTM, or the last `stack` frames and a dense layer
    stack: int = 4  # frames of the frame-stack variant
    conv_channels: tuple[int, int, int, int] = (16, 32, 32, 32)  # conv1, conv2 (shared stream), conv3, conv4
    dense_size: int = 256  # the dense layer after the conv base
    core_size: int = 256  # LSTM cells (or the frame-stack dense layer)
    segmentation_loss: Literal["mse_rgb", "cross_entropy"] = "mse_rgb"  # class colours (paper) or class ids
    space_to_depth: bool = False  # run conv1 (8x8/4) as a 2x2/1 conv on 4x4 pixel blocks (the same function)

    def validate(self, path: str = "") -> None:
        k = functools.partial(_join, path)
        _check(self.stack >= 2, k("stack"), f"must be >= 2, got {self.stack}")
        _check(all(c >= 1 for c in self.conv_channels), k("conv_channels"), f"all must be >= 1, got {list(self.conv_channels)}")
        for name in ("dense_size", "core_size"):
            v = getattr(self, name)
            _check(v >= 1, k(name), f"must be >= 1, got {v}")


@dataclass(frozen=True)
class LossWeights:
    """Weight of each loss term (paper, Table I). A weight of 0 removes the term's computation."""

    actor: float = 1.0
    critic: float = 0.5
    entropy: float = 0.001
    off_policy_critic: float = 1.0
    pixel_control: float = 0.05
    reward_prediction: float = 1.0
    depth: float = 0.1
    segmentation: float = 0.1  # observation segmentation
    target_segmentation: float = 0.1

    def validate(self, path: str = "") -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            _check(v >= 0, _join(path, f.name), f"must be >= 0, got {v}")


@dataclass(frozen=True)
class TrainConfig:
    """Batched A2C with off-policy critic and auxiliary tasks; optimiser; run bookkeeping."""

    total_frames: int = 40_000_000  # f_max: agent steps over all environments
    rollout_length: int = 20  # l
    gamma: float = 0.99
    learning_rate: float = 7e-4
    lr_schedule: Literal["linear", "constant"] = "linear"  # linear: lr * (f_max - f) / f_max
    rmsprop_decay: float = 0.99  # RMSprop alpha
    rmsprop_eps: float = 1e-5
    max_grad_norm: float = 0.5
    replay_size: int = 2000  # replay buffer, steps per environment (whole rollouts are kept)
    replay_batch: int = 16  # replay sequences per update (off-policy critic, pixel control, reward prediction)
    pixel_control_gamma: float = 0.9
    pixel_control_cell: int = 4
    aux_downsize: int = 4  # depth / segmentation targets are downsized by this factor
    timeout_bootstrap: bool = True  # a time-out bootstraps the returns from the critic; false: terminal (paper)
    loss_weights: LossWeights = field(default_factory=LossWeights)
    curriculum: bool = False  # complexity tau rises linearly between two frame counts (paper)
    curriculum_complexity: tuple[float, float] = (0.3, 1.0)  # tau before the first and after the second
    curriculum_frames: tuple[int, int] = (5_000_000, 10_000_000)
    log_every: int = 10  # updates between log lines
    checkpoint_every: int = 500  # updates between checkpoints (and one on exit)
    keep_checkpoints: int = 3

    def validate(self, path: str = "") -> None:
        k = functools.partial(_join, path)
        for name in ("total_frames", "rollout_length", "replay_batch", "pixel_control_cell", "aux_downsize",
                     "log_every", "checkpoint_every", "keep_checkpoints"):
            v = getattr(self, name)
            _check(v >= 1, k(name), f"must be >= 1, got {v}")
        for name in ("gamma", "pixel_control_gamma", "rmsprop_decay"):
            v = getattr(self, name)
            _check(0 <= v <= 1, k(name), f"must be in [0, 1], got {v}")
        for name in ("learning_rate", "rmsprop_eps", "max_grad_norm"):
            v = getattr(self, name)
            _check(v > 0, k(name), f"must be > 0, got {v}")
        lo, hi = self.curriculum_complexity
        _check(0 <= lo <= 1 and 0 <= hi <= 1, k("curriculum_complexity"), f"both must be in [0, 1], got {[lo, hi]}")
        f0, f1 = self.curriculum_frames
        _check(0 <= f0 <= f1, k("curriculum_frames"), f"need 0 <= start <= end, got {[f0, f1]}")
        _check(
            self.replay_size >= self.rollout_length,
            k("replay_size"),
            f"must hold at least one rollout ({k('rollout_length')} = {self.rollout_length}), got {self.replay_size}",
        )


@dataclass(frozen=True)
class PretrainConfig:
    """Supervised pre-training of the conv base with the depth / segmentation heads (paper, Table I)."""

    dataset_size: int = 200_000  # observations at random poses in the training scenes
    epochs: int = 30
    batch_size: int = 64
    learning_rate: float = 1e-3  # Adam

    def validate(self, path: str = "") -> None:
        k = functools.partial(_join, path)
        for name in ("dataset_size", "epochs", "batch_size"):
            v = getattr(self, name)
            _check(v >= 1, k(name), f"must be >= 1, got {v}")
        _check(self.learning_rate > 0, k("learning_rate"), f"must be > 0, got {self.learning_rate}")


@dataclass(frozen=True)
class Config:
    """Root of the configuration tree."""

    seed: int = 0  # master PRNG seed
    env: EnvConfig = field(default_factory=EnvConfig)
    agent: AgentConfig = field(default_factory=AgentConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    pretrain: PretrainConfig = field(default_factory=PretrainConfig)

    def validate(self, path: str = "") -> None:
        _check(0 <= self.seed < 2**31, _join(path, "seed"), f"must be in [0, 2**31), got {self.seed}")
        size = self.env.render.image_size
        for name, factor in (("pixel_control_cell", self.train.pixel_control_cell), ("aux_downsize", self.train.aux_downsize)):
            _check(
                size // factor >= 2,
                _join(path, f"train.{name}"),
                f"{factor} leaves fewer than 2 cells across a {size}-pixel image (env.render.image_size)",
            )


# ---------------------------------------------------------------- generic machinery


@functools.lru_cache(maxsize=None)
def _field_types(cls: type) -> dict[str, Any]:
    """Resolved annotations of the init fields of dataclass `cls`, in field order."""
    hints = get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if f.init}


def _is_section(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _optional_inner(tp: Any) -> Any:
    """X for Optional[X] / X | None, else None."""
    if get_origin(tp) in (Union, types.UnionType):
        args = get_args(tp)
        rest = [a for a in args if a is not type(None)]
        if len(rest) == 1 and len(args) == 2:
            return rest[0]
    return None


def _all_keys(cls: type, path: str = "") -> list[str]:
    """Every dotted key (sections and leaves) of the tree rooted at `cls`."""
    out = []
    for name, tp in _field_types(cls).items():
        key = _join(path, name)
        out.append(key)
        if _is_section(tp):
            out.extend(_all_keys(tp, key))
    return out


def config_keys(cls: Optional[type] = None) -> list[str]:
    """All dotted leaf keys of the dataclass tree `cls` (default `Config`), in field order."""
    cls = Config if cls is None else cls
    out = []
    for name, tp in _field_types(cls).items():
        if _is_section(tp):
            out.extend(_join(name, k) for k in config_keys(tp))
        else:
            out.append(name)
    return out


def _unknown_key_error(cls: type, name: str, path: str, root: Optional[type]) -> ConfigError:
    full = _join(path, name)
    valid = list(_field_types(cls))
    suggestions: list[str] = []
    everywhere = _all_keys(root) if root is not None else []
    # The same name elsewhere in the tree ("env.fovy" -> "env.render.fovy").
    suggestions += [k for k in everywhere if k.rsplit(".", 1)[-1] == name and k != full]
    # A typo of a key in this section.
    suggestions += [_join(path, m) for m in difflib.get_close_matches(name, valid, n=3, cutoff=0.6)]
    if not suggestions and everywhere:
        leaf_names = {}
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


def _coerce(tp: Any, value: Any, key: str, root: Optional[type]) -> Any:
    """Check/convert `value` against annotation `tp`; `key` names it in errors."""
    if _is_section(tp):
        if value is None:
            value = {}
        if not isinstance(value, Mapping):
            raise ConfigError(
                f"{key}: is a section; expected a mapping of its keys "
                f"({', '.join(_field_types(tp))}), got {_describe(value)}",
                key=key,
            )
        return _from_dict(tp, value, key, root)
    if tp is Any:
        return value
    origin = get_origin(tp)
    if origin is Literal:
        choices = get_args(tp)
        for c in choices:
            if value == c and type(value) is type(c):
                return c
        allowed = ", ".join(repr(c) for c in choices)
        raise ConfigError(f"{key}: invalid value {value!r}; allowed values: {allowed}", key=key)
    inner = _optional_inner(tp)
    if inner is not None:
        return None if value is None else _coerce(inner, value, key, root)
    if origin in (Union, types.UnionType):
        raise TypeError(f"unsupported config annotation {tp!r} for {key} (only Optional unions)")
    if origin is tuple:
        args = get_args(tp)
        variadic = len(args) == 2 and args[1] is Ellipsis
        elem_types = None if variadic else args
        what = _type_name(args[0]) if variadic or len(set(args)) == 1 else "values"
        if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
            count = "" if variadic else f"{len(args)} "
            raise ConfigError(f"{key}: expected a list of {count}{what}, got {_describe(value)}", key=key)
        if not variadic and len(value) != len(args):
            raise ConfigError(
                f"{key}: expected a list of {len(args)} {what}, got {len(value)} items: {list(value)!r}", key=key
            )
        types_ = [args[0]] * len(value) if variadic else list(elem_types)
        return tuple(_coerce(t, v, f"{key}[{i}]", root) for i, (t, v) in enumerate(zip(types_, value)))
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.strip().lower() in ("true", "false"):
            return value.strip().lower() == "true"
        raise ConfigError(f"{key}: expected true or false, got {_describe(value)}", key=key)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise ConfigError(f"{key}: expected an integer, got {_describe(value)}", key=key)
        return int(value)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise ConfigError(f"{key}: expected a number, got {_describe(value)}", key=key)
        f = float(value)
        if not math.isfinite(f):
            raise ConfigError(f"{key}: expected a finite number, got {value!r}", key=key)
        return f
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {_describe(value)}", key=key)
        return value
    raise TypeError(f"unsupported config annotation {tp!r} for {key}")


def _type_name(tp: Any) -> str:
    return {int: "integers", float: "numbers", bool: "booleans", str: "strings"}.get(tp, "values")


def _from_dict(cls: type, data: Mapping, path: str, root: Optional[type]) -> Any:
    hints = _field_types(cls)
    for name in data:
        if not isinstance(name, str) or name not in hints:
            raise _unknown_key_error(cls, str(name), path, root)
    kwargs = {}
    defaults = {f.name: f for f in dataclasses.fields(cls)}
    for name, tp in hints.items():
        key = _join(path, name)
        if name in data:
            kwargs[name] = _coerce(tp, data[name], key, root)
        elif _is_section(tp):
            # Build absent sections through the same path so that they are validated
            # too (starting from whatever the field's default produces).
            f = defaults[name]
            if f.default_factory is not dataclasses.MISSING:
                default = f.default_factory()
            elif f.default is not dataclasses.MISSING:
                default = f.default
            else:
                default = None
            kwargs[name] = _coerce(tp, to_dict(default) if default is not None else {}, key, root)
    try:
        obj = cls(**kwargs)
    except TypeError as e:  # a required field without default is missing
        raise ConfigError(f"{path or 'top level'}: {e}", key=path or None) from None
    validate = getattr(obj, "validate", None)
    if callable(validate):
        validate(path)
    return obj


def from_dict(cls: type, data: Optional[Mapping], path: str = "") -> Any:
    """Build and validate an instance of dataclass `cls` from a (possibly partial) mapping.

    Missing keys keep their defaults; sub-sections are built recursively; values are
    coerced and type-checked from the annotations, then each section's `validate(path)`
    runs. `path` is the dotted key of `cls` inside a larger tree, used in messages.
    Raises `ConfigError` for unknown keys, wrong types and invalid values.
    """
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        where = path or "top level"
        raise ConfigError(f"{where}: expected a mapping, got {_describe(data)}", key=path or None)
    return _from_dict(cls, data, path, cls if not path else None)


def to_dict(instance: Any) -> Any:
    """Plain nested dict of a config dataclass tree (tuples become lists), YAML/JSON ready."""
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
    stringy = tp is str or _optional_inner(tp) is str
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
                leaves = ", ".join(_join(full, k) for k in _field_types(tp))
                raise ConfigError(
                    f"{full}: is a section, not a value; override one of its keys instead ({leaves})", key=full
                )
            child = node.get(name)
            if child is None:
                child = node[name] = {}
            elif not isinstance(child, dict):
                raise ConfigError(f"{full}: is a section; expected a mapping, got {_describe(child)}", key=full)
            cls, node, path = tp, child, full
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


def load_config(
    path: Optional[str | os.PathLike] = None, overrides: Sequence[str] = (), *, schema: type = Config
) -> Any:
    """Load a config: defaults <- YAML file at `path` (may be partial; None: none) <- overrides.

    Overrides are "dotted.key=value" strings; the value is parsed as YAML (numbers,
    `true`/`false`, `null`, `[1, 2]` lists), except that string-typed keys take the
    raw text when it does not parse to a string. The merged result is validated once.
    `schema` is the root dataclass (default `Config`).
    """
    if isinstance(overrides, str):
        overrides = [overrides]
    data = copy.deepcopy(_read_yaml(path)) if path is not None else {}
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
