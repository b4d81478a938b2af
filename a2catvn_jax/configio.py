"""Schema-free configuration loading: YAML and dotted overrides -> a validated dataclass tree.

Sits below the schema (`a2catvn_jax.config`, which binds its `Config` as the default
root and does not need to be imported here): every function takes the root dataclass
type, or works on an instance's type. It holds `ConfigError`, the `Section` base
class of the sections, the strict YAML loader and dumper, the parsing and application
of "dotted.key=value" overrides, `from_dict` / `to_dict`, and the translation of
pydantic's structured errors into one-line `ConfigError`s with the likely key meant.

Loading goes file(s) -> dict -> dotted overrides merged into the dict -> one call to
`from_dict`, where pydantic builds and validates the whole tree. Checks involving
several keys are each section's `_cross_checks`, run as a pydantic model validator once
the section's keys are individually valid (so a parent may rely on valid children).
Every problem raises `ConfigError` (a `ValueError`) whose message starts with the full
dotted key; an unknown key comes with the key likely meant.

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
import os
import re
import types
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Annotated, Any, Optional, Union, get_args, get_origin, get_type_hints

import yaml
from pydantic import ConfigDict, TypeAdapter, ValidationError, model_validator

from a2catvn_jax.errors import UserError

__all__ = [
    "ConfigError",
    "from_dict",
    "to_dict",
    "config_keys",
    "load_config",
    "apply_overrides",
    "parse_override",
    "save_config",
]


class ConfigError(ValueError, UserError):
    """Invalid configuration: unknown key, wrong type, bad value, bad file or override.

    `key` is the full dotted key the error is about, or None when it concerns a file
    or an override string as a whole.
    """

    def __init__(self, message: str, key: Optional[str] = None):
        super().__init__(message)
        self.key = key


# ----------------------------------------------------------------------- sections


def _join(path: str, name: str) -> str:
    """Dotted key of `name` inside the section at `path` ("" is the top level)."""
    return f"{path}.{name}" if path else name


class _CrossCheckFailed(ValueError):
    """Raised by the model validator; `from_dict` asks the section for its messages with full keys."""

    def __init__(self, section: Section):
        super().__init__(f"{type(section).__name__}: cross-field check failed")
        self.section = section


class Section:
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


def config_keys(cls: type) -> list[str]:
    """All dotted leaf keys of the dataclass tree `cls`, in field order."""
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
    """'expected a list of 2 integers, got ...' for the tuple annotation `tp` (of a fixed
    length, or `tuple[X, ...]`: one or more, 'expected a list of one or more of ...')."""
    args = get_args(_bare(tp))
    if len(args) == 2 and args[1] is Ellipsis:
        choices = get_args(_bare(args[0]))
        count, what = "one or more", ("of " + ", ".join(map(repr, choices)) if choices else "values")
    else:
        kinds = {_bare(a) for a in args}
        names = {int: "integers", float: "numbers", bool: "booleans", str: "strings"}
        count, what = len(args), names.get(kinds.pop(), "values") if len(kinds) == 1 else "values"
    if isinstance(value, (list, tuple)):
        return f"expected a list of {count} {what}, got {len(value)} items: {list(value)!r}"
    return f"expected a list of {count} {what}, got {_describe(value)}"


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


def flat(data: Mapping, prefix: str = "") -> dict:
    """A nested mapping (a config's `to_dict`) as {"dotted.key": value}."""
    out = {}
    for k, v in data.items():
        key = f"{prefix}.{k}" if prefix else k
        out.update(flat(v, key) if isinstance(v, Mapping) else {key: v})
    return out


def load_config(
    path: Optional[str | os.PathLike | Sequence[str | os.PathLike]] = None, overrides: Sequence[str] = (), *,
    schema: type
) -> Any:
    """Load a config: defaults <- YAML file(s) at `path` (each may be partial; None: none) <- overrides.

    `path` is one file or a list of files; a later file's keys override an earlier
    one's (sections merge key by key, a list is replaced whole). Overrides are
    "dotted.key=value" strings; the value is parsed as YAML (numbers, `true`/`false`,
    `null`, `[1, 2]` lists), except that string-typed keys take the raw text when it
    does not parse to a string. The merged result is validated once. `schema` is the
    root dataclass.
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
    """Write `cfg` as YAML (every key) so that `load_config(path, schema=type(cfg))` gives an equal config."""
    path = os.fspath(path)
    parent = os.path.dirname(path)
    if parent:
        os.makedirs(parent, exist_ok=True)
    text = yaml.dump(to_dict(cfg), Dumper=_Dumper, sort_keys=False, default_flow_style=False)
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("# a2catvn_jax configuration (written by save_config)\n")
        fh.write(text)
