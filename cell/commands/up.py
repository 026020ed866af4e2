"""`cell up`: the whole cell, until Ctrl-C / SIGTERM or --duration."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from typing import Literal

from cell.commands import Command, config_arg, load, register, seconds
from cell.config import CellConfig, ConfigError

RERUN_MODES: tuple[Literal["off", "save", "serve", "spawn"], ...] = ("spawn", "serve", "save", "off")


def with_rerun(config: CellConfig, words: list[str]) -> CellConfig:
    """`--rerun spawn | serve | save PATH.rrd | off`: the recorder's mode for this run."""
    mode, *rest = words
    if mode not in RERUN_MODES or len(rest) != (1 if mode == "save" else 0):
        raise ConfigError("--rerun", "", "expected spawn, serve, save PATH.rrd or off")
    recorder = replace(config.recorder, mode=mode, path=rest[0] if rest else config.recorder.path)
    return _recording(config, recorder)


def with_bag(config: CellConfig, path: str) -> CellConfig:
    """`--bag DIR`: the run written as a ROS 2 bag too (cell.recorder.bag)."""
    return _recording(config, replace(config.recorder, bag=path))


def _recording(config: CellConfig, recorder) -> CellConfig:
    """The recorder as given, and its service run on this host if it records anything."""
    run = config.services.run
    if (recorder.mode != "off" or recorder.bag) and "recorder" not in run:
        run = [*run, "recorder"]
    return replace(config, recorder=recorder, services=replace(config.services, run=run))


def arguments(p: argparse.ArgumentParser) -> None:
    config_arg(p)
    p.add_argument("--duration", type=seconds, metavar="S", help="stop cleanly after S seconds")
    p.add_argument(
        "--layout",
        choices=["groups", "single", "each"],
        help="services in processes: groups (the packet path in processes of its own, pinned, real-time "
        "priority; the rest in one), single (one process: debugging), each (one per service); "
        "default: [services] layout",
    )
    p.add_argument("--processes", action="store_true", help="the same as --layout each")
    p.add_argument(
        "--rerun",
        nargs="+",
        metavar="MODE",
        help="draw the run in Rerun: spawn (local viewer), serve (web viewer on 127.0.0.1), "
        "save PATH.rrd, or off (default: [recorder] mode)",
    )
    p.add_argument(
        "--bag",
        metavar="DIR",
        help="write the run as a ROS 2 bag (rosbag2, MCAP) in DIR as well ([recorder] bag)",
    )
    p.add_argument("--watch-stdin", action="store_true", help=argparse.SUPPRESS)  # (set by child_cell)
    p.add_argument(
        "--verbose", "-v", action="store_true", help="at the stop, every service's counters below the table"
    )


def run(args: argparse.Namespace) -> int:
    from cell import aio, launcher
    from cell.service import check_all

    config = load(args)
    if args.rerun:
        config = with_rerun(config, args.rerun)
    if args.bag:
        config = with_bag(config, args.bag)
    layout: Literal["groups", "single", "each"] | None = "each" if args.processes else args.layout
    if layout is not None:
        config = replace(config, services=replace(config.services, layout=layout))
    check_all(config)  # unknown services are config errors (exit 2), before anything starts
    if config.recorder.mode == "serve" and "recorder" in config.services.run:
        from cell.recorder.serve import taken

        if why := taken():  # (one line now, not the recorder failing at each restart)
            print(f"cell up: {why}", file=sys.stderr)
            return 2
    return aio.run(
        launcher.up(
            config,
            duration=args.duration,
            log_level=args.log_level,
            counters=args.verbose,
            watch_stdin=args.watch_stdin,
        )
    )


register(
    Command("up", "run the whole cell until Ctrl-C (or --duration)", arguments, run, rank=0, hard_exit=True)
)
