"""`cell teleop`: bilateral teleoperation over the Responsive Link (docs/teleop.md)."""

from __future__ import annotations

import argparse
import sys

from cell.commands import Command, json_arg, register
from cell.jsonfields import json_line


def _pushes(text: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected forces in N separated by commas (got {text!r})") from None
    if not out or any(not 0.5 < v <= 20 for v in out):
        raise argparse.ArgumentTypeError("each push aims at more than 0.5 N and at most 20 N")
    return out


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--object", choices=["sponge", "wood"], default="sponge")
    p.add_argument("--delay-ms", type=float, default=0.0, metavar="D", help="added data-link delay")
    p.add_argument("--jitter-ms", type=float, default=0.0, metavar="J", help="+/- J ms on that delay")
    p.add_argument("--mode", choices=["modified", "conventional", "unilateral"], default="modified")
    p.add_argument(
        "--drive",
        choices=["twin", "usual"],
        default="twin",
        help="the joints' drives (usual: Coulomb friction)",
    )
    p.add_argument(
        "--gear",
        type=float,
        help="usual drive: the gear ratio the motor's friction is seen through (default 100)",
    )
    p.add_argument(
        "--pushes",
        type=_pushes,
        default=None,
        metavar="N,N,...",
        help="the operator's pushes: the force each aims at, in N (default 4,6,5,6)",
    )
    p.add_argument("--estop-at", type=float, metavar="S", help="the console's e-stop, S seconds after start")
    p.add_argument(
        "--rerun", nargs="+", metavar="MODE", help="spawn, serve, save PATH.rrd or off (default: off)"
    )
    p.add_argument("--png", metavar="PATH", help="force and position over time, as a PNG")
    json_arg(p)


def run(args: argparse.Namespace) -> int:
    from cell.teleop import experiment
    from cell.teleop.experiment import USUAL_GEAR
    from cell.teleop.law import Mode
    from cell.teleop.realtime import Setup
    from cell.teleop.twindrive import COULOMB

    if args.jitter_ms > args.delay_ms:
        print("error: --jitter-ms must not exceed --delay-ms", file=sys.stderr)
        return 2
    setup = Setup(
        obj=args.object,
        delay_ms=args.delay_ms,
        jitter_ms=args.jitter_ms,
        mode=Mode[args.mode.upper()],
        coulomb_nm=COULOMB * (args.gear or USUAL_GEAR) if args.drive == "usual" else 0.0,
        estop_at_s=args.estop_at,
        **({"pushes": args.pushes} if args.pushes else {}),
    )
    try:
        r = experiment.teleop(setup, args.rerun, args.png)
    except RuntimeError as exc:  # a side died or never came up: say which, no traceback
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if "peak_force_remote_n" in r:
        print(
            f"{args.object}: peak force local {r['peak_force_local_n']:.2f} N, "
            f"remote {r['peak_force_remote_n']:.2f} N; "
            f"|f_l + f_r| rms {r['force_error_rms_n']:.3f} N (max {r['force_error_max_n']:.2f}); "
            f"tip z p-p remote {r['position_pp_remote_mm']:.2f} mm, local {r['position_pp_local_mm']:.2f} mm"
        )
    print(
        f"loops: period p50 {r['period_p50_ms']:.3f} ms, p99 {r['period_p99_ms']:.3f} ms, "
        f"missed {r['missed_periods_pct']:.3f}% ({r['placement']['local']} / {r['placement']['remote']})"
    )
    if "estop" in r:
        e = r["estop"]
        print(
            f"e-stop taken after {e['taken_ms']} ms (skew {e['skew_ms']} ms), "
            f"still after {e['still_after_ms']} ms"
        )
    if args.png:
        print(f"figure: {r['png']}")
    if args.json:
        print(json_line(r))
    return 0


register(
    Command(
        "teleop",
        "bilateral teleoperation over the Responsive Link: an operator pushes an object through "
        "two arms, and feels it",
        arguments,
        run,
        rank=35,
        description="Two MuJoCo arms, one process each, run the Fig. 14 force-reflecting servo at 1 ms over "
        "the Responsive Link (docs/teleop.md). A scripted operator pushes the object several times.",
    )
)
