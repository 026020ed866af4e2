"""`cell config show`: the effective configuration as TOML."""

from __future__ import annotations

import argparse

from cell.commands import Command, config_arg, load, register


def arguments(p: argparse.ArgumentParser) -> None:
    csub = p.add_subparsers(dest="config_command", required=True, metavar="ACTION")
    q = csub.add_parser("show", help="print the effective configuration as TOML")
    config_arg(q)


def run(args: argparse.Namespace) -> int:
    import tomli_w

    config = load(args)
    data = config.to_dict()
    for robot, table in zip(config.robots, data.get("robots", []), strict=True):
        table["ur_address"] = robot.ur_host  # (the address it answers on, "" resolved)
    print(f"# effective configuration: {config.source} over the embedded default")
    backend, why = config.dataplane.chosen()
    ticks = sorted({r.tick for r in config.robots if r.backend != "ur"})
    print(f"# data plane: {backend} ({why}); robots' tick: {', '.join(ticks) or '-'} (docs/robots.md)\n")
    print(tomli_w.dumps(data), end="")
    return 0


register(Command("config", "inspect the configuration", arguments, run, rank=30))
