"""`cell bench TARGET`: the benches of cell.bench.registry, each next to a baseline in the same run."""

from __future__ import annotations

import argparse
import sys

from cell.commands import Command, json_arg, literal, register
from cell.jsonfields import json_line


def arguments(p: argparse.ArgumentParser) -> None:
    from cell.bench.registry import discover

    bsub = p.add_subparsers(dest="bench_command", required=True, metavar="TARGET")
    for bench in discover().values():
        q = bsub.add_parser(bench.name, help=literal(bench.help), description=literal(bench.description))
        json_arg(q)
        q.add_argument(
            "--results", metavar="FILE", help="also write the figures into FILE's section for this bench"
        )
        bench.arguments(q)
        q.set_defaults(bench=bench)


def run(args: argparse.Namespace) -> int:
    """A bench's figures as text, then with --json as one JSON line, last."""
    figures = args.bench.run(args)
    if figures.text:
        print(figures.text)
    if args.results and figures.exit_code == 0:
        from cell.bench import results

        argv = [a for a in sys.argv[1:] if a != "--json"]
        name = args.bench.name
        results.write(
            args.results, figures.section or name, argv or ["bench", name], figures.result.to_json()
        )
    if args.json:
        print(json_line(figures.result.to_json()))
    return figures.exit_code


register(Command("bench", "measure hot paths next to a baseline in the same run", arguments, run, rank=45))
