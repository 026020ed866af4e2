"""`cell estop | stop | resume`: one order on the Responsive Link, then the robots' reports."""

from __future__ import annotations

import argparse
import sys

from cell.commands import Command, config_arg, load, register, seconds

ORDERS = {
    "estop": "emergency stop over the Responsive Link: the drives brake at once",
    "stop": "stop over the Responsive Link on the data plane's ramp (the drives stay on)",
    "resume": "release robots stopped over the Responsive Link",
}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("robots", nargs="*", metavar="ROBOT")
    config_arg(p)
    p.add_argument("--no-wait", action="store_true", help="send the order and return")
    p.add_argument("--timeout", type=seconds, default=5.0, metavar="S", help="wait at most S (default 5)")


def run(args: argparse.Namespace) -> int:
    from cell import aio
    from cell.rlink.client import EventClient

    config = load(args)
    known = {r.name for r in config.robots} | {str(r.id) for r in config.robots}
    unknown = [r for r in args.robots if r not in known]
    if unknown:
        robots = ", ".join(f"{r.name} ({r.id})" for r in config.robots)
        print(
            f"cell {args.command}: no robot {unknown[0]!r} in this cell (robots: {robots})", file=sys.stderr
        )
        return 2

    async def go() -> dict[int, float]:
        async with EventClient(config) as client:
            order = getattr(client, args.command)
            return await order(args.robots or None, wait=not args.no_wait, timeout=args.timeout)

    try:
        took = aio.run(go())
    except KeyError as exc:
        print(f"cell {args.command}: {exc.args[0]}", file=sys.stderr)
        return 2
    except TimeoutError as exc:
        print(f"cell {args.command}: {exc}", file=sys.stderr)
        return 1
    names = {r.id: r.name for r in config.robots}
    what = "released" if args.command == "resume" else "standing still"
    for rid, ms in sorted(took.items()):
        print(f"{names.get(rid, rid)}: {what} {ms:.1f} ms after the order")
    named = set(args.robots)
    for r in config.robots:
        if not args.no_wait and r.id not in took and (not named or {r.name, str(r.id)} & named):
            print(f"{r.name}: ordered (on host {r.host}, whose robots the data plane stops: no report)")
    if args.no_wait:
        print(f"{args.command} sent")
    return 0


for _rank, (_name, _what) in enumerate(ORDERS.items(), start=10):
    register(
        Command(
            _name,
            _what,
            arguments,
            run,
            rank=_rank,
            description=f"{_what[0].upper()}{_what[1:]}. Robots by name or id (none: every robot); "
            "waits until each reports (exit code 1 if one does not).",
        )
    )
