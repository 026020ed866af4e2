"""`cell chaos`: the fault campaign (docs/faults.md)."""

from __future__ import annotations

import argparse

from cell.commands import Command, json_arg, register
from cell.jsonfields import json_line


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rounds", type=int, default=1, help="campaign rounds (default 1)")
    p.add_argument(
        "--only", nargs="+", metavar="TEXT", help="only the faults whose name contains one of these"
    )
    p.add_argument(
        "--config",
        "-c",
        metavar="FILE",
        help="a cell config merged over the default before the campaign's own settings (e.g. "
        "examples/xdp.toml: the data plane in the kernel)",
    )
    p.add_argument(
        "--hog",
        action="store_true",
        help="a busy process at the normal priority on every core for the whole campaign (a host's "
        "other work)",
    )
    json_arg(p)


def run(args: argparse.Namespace) -> int:
    import asyncio

    from cell.chaos.campaign import campaign

    print(f"{'RD':>2} {'FAULT':<28} {'HELD?':<7} {'DETECT':>8} {'RECOVER':>8}  WHAT FAILED")
    from cell.config import ConfigError, load_config

    if args.config:
        try:
            load_config(args.config)  # (a bad file is said in one line before anything starts)
        except ConfigError as exc:
            print(f"cell chaos: {exc}")
            return 2
    import contextlib

    from cell.hog import hog

    with hog() if args.hog else contextlib.nullcontext():
        result = asyncio.run(
            campaign(
                args.rounds, args.only, log_fn=lambda line: print(line, flush=True), config_path=args.config
            )
        )
    print(f"{result['held']} of {result['faults']} faults held every promise ({result['rounds']} round(s))")
    if args.json:
        print(json_line(result))
    return 0 if result["failed"] == 0 else 1


register(
    Command(
        "chaos",
        "fault campaign: the default cell in --processes mode, driven while faults hit it",
        arguments,
        run,
        rank=40,
        description="Kills and hangs each service, takes the bus away, slows the controller's link, mutes a "
        "robot, then some at once, each mid-motion; prints per fault whether the cell's promises held, the "
        "time to detect and to recover (docs/faults.md). Exit code 0 only if every promise held.",
    )
)
