"""`cell modular status | plug MODULE | unplug MODULE | move ...`: the modular robot (service `modular`)."""

from __future__ import annotations

import argparse
import math
import sys

from cell.commands import Command, config_arg, load, register, seconds


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=["status", "plug", "unplug", "move"])
    p.add_argument("module", nargs="?", metavar="MODULE", help="plug / unplug: j1 .. j6")
    config_arg(p)
    goal = p.add_mutually_exclusive_group()
    goal.add_argument("--joints", type=float, nargs=6, metavar="RAD", help="move: a joint goal")
    goal.add_argument("--tool", type=float, nargs=3, metavar="M", help="move: a tool position (x y z)")
    goal.add_argument("--path", choices=["pick-and-place", "circle"], help="move: a named path from home")
    p.add_argument("--speed", type=float, default=0.0, metavar="RAD/S", help="move: the fastest joint's peak")
    p.add_argument(
        "--timeout", type=seconds, default=120.0, metavar="S", help="give up after S (default 120)"
    )


def show(st) -> str:
    cycle = st.transport == "cycle"  # (the SnP cycle's processes: each module has a clock of its own)
    lines = [f"{'MODULE':<8}{'STATE':<11}{'GUESSED':>8}  [C, D] BY" + ("  CLOCK - MASTER'S" if cycle else "")]
    lines += [
        f"{m.name:<8}{m.state:<11}{m.guessed:>8}  {m.where:<9}"
        + (f"{m.clock_offset_us:>8.2f} us" if cycle and math.isfinite(m.clock_offset_us) else "")
        for m in st.modules
    ]
    what = f"{st.period_ms:g} ms SnP cycles, [A, B, C, D]" if cycle else "cycles, VDC arithmetic"
    lines.append(
        f"{st.cycles:,} {what} {st.cycle_us_mean:.0f} us a cycle (max {st.cycle_us_max:.0f}; "
        f"{st.late_cycles:,} late); tool at {', '.join(f'{x * 1e3:.1f}' for x in st.tool)} mm"
    )
    lines.append(f"moving: {st.motion}" if st.motion else f"holding{': ' + st.stopped if st.stopped else ''}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from cell import aio
    from cell.bus import Bus, BusError, FaultCode, RemoteError
    from cell.modular.client import ModularClient

    config = load(args)
    if args.action in ("plug", "unplug") and not args.module:
        print(f"cell modular {args.action}: which module? (j1 .. j6)", file=sys.stderr)
        return 2
    if args.action == "move" and not (args.joints or args.tool or args.path):
        print("cell modular move: give --joints, --tool or --path", file=sys.stderr)
        return 2

    async def go() -> str:
        async with Bus.connect(config.bus, "cell-modular") as bus:
            m = ModularClient(bus)
            if args.action == "move":
                r = await m.move(args.joints or (), tool=args.tool or (), path=args.path or "",
                                 speed=args.speed, timeout=args.timeout)  # fmt: skip
                return (
                    f"{r.path}: {r.duration_s:.2f} s, tool error max {r.tool_error_mm_max:.3f} mm, "
                    f"rms {r.tool_error_mm_rms:.3f} mm, {r.guessed} messages guessed"
                )
            if args.action == "status":
                return show(await m.status(timeout=min(args.timeout, 5.0)))
            return show(await getattr(m, args.action)(args.module))

    try:
        print(aio.run(go()))
    except RemoteError as exc:
        print(f"cell modular {args.action}: {exc.code}: {exc.message}", file=sys.stderr)
        return 2 if exc.code in (FaultCode.REFUSED, FaultCode.UNKNOWN_MODULE) else 1
    except (BusError, TimeoutError) as exc:
        print(
            f"cell modular {args.action}: no modular robot answered ({exc or 'timed out'})", file=sys.stderr
        )
        return 1
    return 0


register(
    Command(
        "modular",
        "the modular robot (seed 002): its modules, plug / unplug one, move it",
        arguments,
        run,
        rank=40,
        description="Exit code: 0 done, 1 no modular robot answered (or a module was lost on the way), "
        "2 refused.",
    )
)
