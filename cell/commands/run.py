"""`cell run SCRIPT`: a task script's `async def main(cell)` against a running cell."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cell.commands import Command, config_arg, load, register


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("script", help="a Python file defining async def main(cell)")
    config_arg(p)
    p.add_argument("--up", action="store_true", help="start the cell first (and stop it after)")


def run(args: argparse.Namespace) -> int:
    from cell import aio
    from cell.master import run_script

    config = load(args)
    path = Path(args.script)
    if not path.is_file():
        print(f"cell run: no such script: {path}", file=sys.stderr)
        return 2
    return aio.run(run_script(path, config, Path(args.config) if args.config else None, up=args.up))


register(
    Command(
        "run", "run a task script's `async def main(cell)` against a running cell", arguments, run, rank=2
    )
)
