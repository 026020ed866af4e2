"""The `cell` commands: one module each in this package, each registering itself.

A command module declares what `cell NAME --help` shows and what runs:

    def arguments(p: argparse.ArgumentParser) -> None: ...
    def run(args: argparse.Namespace) -> int: ...
    register(Command("name", "one line of help", arguments, run, rank=50))

Modules here are imported to list the commands, so they import only the
standard library and cell.config at the top, and what their run() needs inside
it.  A new command is a new module; nothing else changes.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass

from cell.config import CellConfig, load_config

EXIT_CONFIG = 2


@dataclass(frozen=True)
class Command:
    name: str
    help: str
    arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    rank: int = 50  # place in `cell --help`: the everyday commands first
    description: str | None = None
    # skip the interpreter's teardown after run() (long-lived runtimes: extension modules such as
    # ruckig's nanobind print reference-leak reports at exit that are not ours to fix)
    hard_exit: bool = False


COMMANDS: dict[str, Command] = {}


def register(command: Command) -> Command:
    if command.name in COMMANDS:
        raise ValueError(f"two commands named {command.name!r}")
    COMMANDS[command.name] = command
    return command


def discover() -> dict[str, Command]:
    """Every command of this package, by rank then name."""
    for info in pkgutil.iter_modules(__path__):
        importlib.import_module(f"{__name__}.{info.name}")
    return dict(sorted(COMMANDS.items(), key=lambda kv: (kv[1].rank, kv[0])))


def config_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config",
        "-c",
        metavar="FILE",
        help="TOML merged over the embedded default (default: the embedded one)",
    )
    p.add_argument("--host", metavar="NAME", help="which of the config's [hosts] this is (a cell of several)")


def seconds(text: str) -> float:
    """An argparse type: a duration, s, finite and > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be > 0 s (got {text})")
    return value


def json_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="also print the figures as one JSON line, last")


def load(args: argparse.Namespace, overrides: dict | None = None) -> CellConfig:
    """The effective config of a command: --config over the default, --host and `overrides` on top."""
    host = getattr(args, "host", None)
    if host is not None:
        overrides = {**(overrides or {}), "cell": {"host": host}}
    return load_config(args.config, overrides=overrides)


def literal(text: str | None) -> str | None:
    """Help text as argparse prints it literally (it formats help with %: "0.1% late" broke it)."""
    return None if text is None else text.replace("%", "%%")
