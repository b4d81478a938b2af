"""What every command line shares: the configuration arguments and one-line errors.

    parser = argparse.ArgumentParser(...)
    cli.add_config_args(parser)              # --config PATH [PATH ...], --set KEY=VALUE ...
    args = parser.parse_args()
    with cli.errors(parser, code=2):
        cfg = cli.config_from_args(args)     # a UserError becomes "error: ..." and exit 2
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
from typing import Any, Callable, Iterator, Optional, Sequence

from a2catvn_jax.config import Config, load_config
from a2catvn_jax.errors import UserError

MAX_MESSAGE = 2000  # characters of an error message a command prints (orbax's can list a whole tree)
SET_HELP = "override config keys, e.g. --set env.num_envs=32 env.render.culling=false (repeatable)"


def add_config_args(parser: argparse.ArgumentParser, *, config: bool = True,
                    help: str = SET_HELP) -> argparse.ArgumentParser:
    """Add `--config PATH [PATH ...]` (unless `config` is False) and `--set KEY=VALUE
    [KEY=VALUE ...]` (repeatable) to `parser`.

    Parsed into `args.config` (a list of paths, or None) and `args.overrides` (list of
    lists; read them with `overrides_of`). Because `--config` and `--set` take several
    values, put positional arguments before them or separate them with `--`.
    """
    group = parser.add_argument_group("configuration")
    if config:
        group.add_argument("--config", metavar="PATH", nargs="+", default=None,
                           help="YAML config file(s), each may list only some keys; a later file's keys override an "
                                "earlier one's, e.g. --config configs/paper.yaml configs/presets/authors_network.yaml")
    group.add_argument("--set", dest="overrides", metavar="KEY=VALUE", nargs="+", action="append", default=[], help=help)
    return parser


def overrides_of(args: argparse.Namespace) -> list[str]:
    """The `--set` overrides of a namespace parsed with `add_config_args`, in order."""
    overrides: list[str] = []
    for item in getattr(args, "overrides", None) or []:
        if isinstance(item, str):
            overrides.append(item)
        else:
            overrides.extend(item)
    return overrides


def config_from_args(args: argparse.Namespace, *, schema: type = Config,
                     default: Optional[str | os.PathLike] = None) -> Any:
    """The configuration of a namespace parsed with `add_config_args`: the `--config`
    files merged in order (or `default` when none was given; None: the built-in
    defaults) with the overrides."""
    path = getattr(args, "config", None)
    return load_config(default if path is None else path, overrides_of(args), schema=schema)


def one_line(message: str, limit: int = MAX_MESSAGE) -> str:
    """`message` cut to `limit` characters."""
    message = str(message)
    return message if len(message) <= limit else message[:limit] + " ..."


@contextlib.contextmanager
def errors(parser: argparse.ArgumentParser, code: int = 1, kinds: Sequence[type] = (UserError,)) -> Iterator[None]:
    """Turn an error of `kinds` (default: any `UserError`) raised inside the block into
    `error: MESSAGE` on stderr and exit status `code`."""
    try:
        yield
    except tuple(kinds) as e:
        parser.exit(code, f"error: {one_line(str(e))}\n")


def run_stoppable(main: Callable[[], None]) -> None:
    """Run a command whose work stops with a checkpoint on Ctrl-C (`python -m ...`'s entry).
    Once `main` is over, a further Ctrl-C or SIGTERM while the process exits (a second
    press that came after the stop had already finished; a scheduler's signal that reaches
    one process of a run after another's stopped them all) is ignored rather than a
    traceback or a process gone from its peers' shutdown."""
    try:
        main()
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
