"""`cell status`: a running cell's services, health, uptime and counters."""

from __future__ import annotations

import argparse
import json
import sys

from cell.commands import Command, config_arg, load, register, seconds
from cell.status import Health


def arguments(p: argparse.ArgumentParser) -> None:
    config_arg(p)
    p.add_argument(
        "--timeout", type=seconds, default=2.0, metavar="S", help="give up after S seconds (default 2)"
    )
    p.add_argument("--json", action="store_true", help="print the status as JSON (one line)")
    p.add_argument(
        "--indent", type=int, nargs="?", const=2, metavar="N", help="with --json: indented N spaces (2)"
    )


def modular_modules(st) -> list[str]:
    """The modular robot's modules and their states, from its service's counters ("j3 unplugged")."""
    counters = {k: v for s in st.services if s.name == "modular" for k, v in s.last.counters.items()}
    if not counters:
        return []
    from cell.modular.robot import STATES, ModularRobot  # (MuJoCo and all: only for a modular robot)

    return [
        f"{name} {STATES[int(counters[key])]}"
        for name in ModularRobot.NAMES
        if (key := f"modular.{name}.state") in counters
    ]


def run(args: argparse.Namespace) -> int:
    from google.protobuf import json_format

    from cell import aio, launcher
    from cell.bus import BusError
    from cell.status import format_status

    config = load(args)
    try:
        st = aio.run(launcher.fetch_status(config, args.timeout))
    except BusError as exc:
        print(f"cell status: no cell answered ({exc})", file=sys.stderr)
        return 1
    if args.json:
        print(
            json.dumps(
                json_format.MessageToDict(
                    st, always_print_fields_with_no_presence=True, preserving_proto_field_name=True
                ),
                indent=args.indent,
            )
        )
    else:
        print(format_status(st))
        modules = modular_modules(st)
        if modules:
            print(f"\nMODULAR ROBOT ({'  '.join(modules)})")
        if config.ur.interfaces and any(s.name.split("@")[0] == "robots" for s in st.services):
            ur = config.ur
            ports = f"RTDE {ur.rtde_port}, dashboard {ur.dashboard_port}, URScript {ur.primary_port}"
            ports += f"-{ur.realtime_port}"
            print(f"\nUR interfaces ({ports}):")
            counters = {
                k: v
                for s in st.services
                if s.name.split("@")[0] == "robots"
                for k, v in s.last.counters.items()
            }
            for r in config.robots:
                line = f"  {r.name:<10} {r.ur_host:<16} {r.model} ({r.backend})"
                if r.backend == "ur":  # (its controller's: emulated here, or a real one the daemon reaches)
                    where = f"emulated, {r.ur_emulate}" if r.ur_emulate else "a UR controller"
                    running = counters.get(f"daemon.{r.name}.running")
                    state = (
                        "?" if running is None else "running" if running else "not running (the log says why)"
                    )
                    line = (
                        f"  {r.name:<10} {r.ur_host:<16} {r.model} ({where}; the daemon's program: {state})"
                    )
                print(line)
    return 0 if all(s.health == Health.OK for s in st.services) else 3


register(
    Command(
        "status",
        "list a running cell's services, health, uptime and counters",
        arguments,
        run,
        rank=3,
        description="Exit code: 0 every service ok, 1 no cell answered, 3 some service not ok.",
    )
)
