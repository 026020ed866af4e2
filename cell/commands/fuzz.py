"""`cell fuzz`: bad input at scale against every listener of the default cell (docs/faults.md)."""

from __future__ import annotations

import argparse

from cell.commands import Command, json_arg, register
from cell.jsonfields import json_line


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--inputs", type=int, default=1_000_000, help="inputs per listener (default 10^6)")
    p.add_argument("--seed", type=int, default=1, help="the seed of every generator (default 1)")
    p.add_argument(
        "--only", nargs="+", metavar="TEXT", help="only the targets whose name contains one of these"
    )
    json_arg(p)


def run(args: argparse.Namespace) -> int:
    import asyncio

    from cell.fuzz.campaign import campaign

    result = asyncio.run(
        campaign(args.inputs, args.seed, args.only, log_fn=lambda line: print(line, flush=True))
    )
    growth = max(result["memory_growth_mb"].values(), default=0.0)
    print(
        f"{sum(result['inputs'].values()):,} inputs: {result['crashes']} crashes, {result['hangs']} hangs, "
        f"answered in time after each: {'yes' if result['answered_in_time'] else 'NO'}, "
        f"largest memory growth {growth:.1f} MB"
    )
    if args.json:
        print(json_line(result))
    return 0 if result["ok"] else 1


register(
    Command(
        "fuzz",
        "bad input at scale: every listener of the default cell, then attacks on its resources",
        arguments,
        run,
        rank=41,
        description="Sends --inputs generated inputs (hypothesis seeds of each wire format, mutated) to the "
        "skill servers, the data plane, SnP, the Responsive Link, the bus and the config loader, probing "
        "after every burst; then 10,000 idle TCP connections, a 1 byte/s client, a 100 MB line and a UDP "
        "flood. Exit code 0 only with no crash, no hang, every probe in its usual time and memory bounded.",
    )
)
