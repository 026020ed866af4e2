"""The benches of `cell bench`: each module of cell.bench (or a user's package, through the entry-point
group "cell.benches") registers its own, with its arguments and its entry point.

    def _arguments(p: argparse.ArgumentParser) -> None: ...
    def _main(args: argparse.Namespace) -> Figures: ...
    register(Bench("name", "one line of help", _arguments, _main))

`--json` is every bench's: Figures.result.to_json() is printed as one JSON line, last (the keys
the benches' issues name).  A bench's result is a dataclass of its figures (as ruckig's Result):
cell.jsonfields.JsonFields gives it a to_json() of its fields.  A bench module is imported only
when `cell bench` runs.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points

from cell.jsonfields import JsonFields, Result


@dataclass
class Failed(JsonFields):
    """A bench that could not run, and why (its JSON line: {"error": why})."""

    error: str


@dataclass
class Figures:
    """What a bench measured: its figures (the JSON line), their text, and the command's exit code."""

    result: Result
    text: str = ""
    exit_code: int = 0
    section: str = ""  # its section of the results page, if not the bench's name (a mode of its own)


@dataclass(frozen=True)
class Bench:
    name: str
    help: str
    arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], Figures]
    description: str | None = None


BENCHES: dict[str, Bench] = {}
_PACKAGE = "cell.bench"
_found: list[bool] = []


def register(bench: Bench) -> Bench:
    if BENCHES.get(bench.name, bench) is not bench:
        raise ValueError(f"two benches named {bench.name!r}")
    BENCHES[bench.name] = bench
    return bench


def discover() -> dict[str, Bench]:
    """Every bench: the modules of cell.bench, then the entry points of group "cell.benches" (each a
    module that registers its bench, or a Bench)."""
    if not _found:
        pkg = importlib.import_module(_PACKAGE)
        for info in pkgutil.iter_modules(pkg.__path__):
            importlib.import_module(f"{_PACKAGE}.{info.name}")
        for ep in entry_points(group="cell.benches"):
            obj = ep.load()
            if isinstance(obj, Bench):
                register(obj)
        _found.append(True)
    return dict(sorted(BENCHES.items()))


def log(line: str) -> None:
    """Benches' progress lines, as they come."""
    print(line, flush=True)
