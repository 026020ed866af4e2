"""`cell service`: some services, or one process group, in this process against a running bus."""

from __future__ import annotations

import argparse
import sys

from cell.commands import EXIT_CONFIG, Command, config_arg, load, register


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("names", nargs="*", metavar="NAME", help="services to run")
    p.add_argument("--group", metavar="GROUP", help="run this process group's services instead")
    config_arg(p)
    p.add_argument("--watch-stdin", action="store_true", help=argparse.SUPPRESS)  # set by `cell up`


def run(args: argparse.Namespace) -> int:
    from cell import aio, launcher
    from cell.service import load_all

    if bool(args.names) == bool(args.group):
        print("cell service: name services, or one process group with --group", file=sys.stderr)
        return EXIT_CONFIG
    config = load(args)
    load_all(config, args.names)  # unknown names are config errors, before anything starts
    return aio.run(launcher.service(config, args.names, group=args.group, watch_stdin=args.watch_stdin))


register(
    Command(
        "service",
        "run services in one process against a running bus",
        arguments,
        run,
        rank=20,
        description="Runs the named services (built-in, e.g. robots, or [services.plugins] names) in "
        "one process, or with --group the services of a [[services.groups]] entry ('main': those no "
        "group names). The process takes the CPUs and priority of its group, as `cell up` gives them.",
        hard_exit=True,
    )
)
