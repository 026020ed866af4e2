"""The `cell` command line."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from google.protobuf import json_format

from cell import __version__, aio
from cell.config import CellConfig, ConfigError, load_config

EXIT_CONFIG = 2


def _config_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config",
        "-c",
        metavar="FILE",
        help="TOML merged over the embedded default (default: the embedded one)",
    )
    p.add_argument("--host", metavar="NAME", help="which of the config's [hosts] this is (a cell of several)")


def _load(args: argparse.Namespace, overrides: dict | None = None) -> CellConfig:
    """The effective config of a command: --config over the default, --host and `overrides` on top."""
    host = getattr(args, "host", None)
    if host is not None:
        overrides = {**(overrides or {}), "cell": {"host": host}}
    return load_config(args.config, overrides=overrides)


def _cmd_up(args: argparse.Namespace) -> int:
    from cell import launcher
    from cell.services import check_all

    config = _load(args)
    if args.rerun:
        config = _with_rerun(config, args.rerun)
    layout = "each" if args.processes else args.layout
    if layout is not None:
        config = replace(config, services=replace(config.services, layout=layout))
    check_all(config)  # unknown services are config errors (exit 2), before anything starts
    return aio.run(launcher.up(config, duration=args.duration, log_level=args.log_level))


def _with_rerun(config: CellConfig, words: list[str]) -> CellConfig:
    """`--rerun spawn | serve | save PATH.rrd | off`: the recorder's mode for this run."""
    mode, *rest = words
    if mode not in ("spawn", "serve", "save", "off") or len(rest) != (1 if mode == "save" else 0):
        raise ConfigError("--rerun", "", "expected spawn, serve, save PATH.rrd or off")
    recorder = replace(config.recorder, mode=mode, path=rest[0] if rest else config.recorder.path)
    run = config.services.run
    if mode != "off" and "recorder" not in run:
        run = [*run, "recorder"]
    return replace(config, recorder=recorder, services=replace(config.services, run=run))


def _cmd_service(args: argparse.Namespace) -> int:
    from cell import launcher
    from cell.services import load_all

    if bool(args.names) == bool(args.group):
        print("cell service: name services, or one process group with --group", file=sys.stderr)
        return EXIT_CONFIG
    config = _load(args)
    load_all(config, args.names)  # unknown names are config errors, before anything starts
    return aio.run(launcher.service(config, args.names, group=args.group, watch_stdin=args.watch_stdin))


def _cmd_run(args: argparse.Namespace) -> int:
    from cell.master import run_script

    config = _load(args)
    path = Path(args.script)
    if not path.is_file():
        print(f"cell run: no such script: {path}", file=sys.stderr)
        return 2
    return aio.run(run_script(path, config, Path(args.config) if args.config else None, up=args.up))


def _cmd_demo(args: argparse.Namespace) -> int:
    """The main job: the default cell, a bundled task script, a recording, a summary."""
    import shutil
    import subprocess
    import time

    from cell import demo
    from cell.master import run_script

    stamp = time.strftime("%Y%m%d-%H%M%S")
    rrd = Path(args.out or f"runs/{stamp}.rrd").resolve()
    rrd.parent.mkdir(parents=True, exist_ok=True)
    config = _load(args, {"recorder": {"mode": "save", "path": str(rrd)}})
    config = _with_rerun(config, ["save", str(rrd)])
    effective = rrd.with_suffix(".toml")
    effective.write_text(config.to_toml())
    print(f"cell demo: the default cell, recorded to {rrd}", flush=True)
    rc = aio.run(run_script(Path(demo.__file__), config, effective, up=True))
    rerun = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
    if rrd.exists() and Path(rerun).exists():
        check = subprocess.run(
            [rerun, "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120
        )
        verdict = "verified" if check.returncode == 0 else f"NOT verified: {check.stderr.strip()[-300:]}"
        print(f"recording {rrd} ({rrd.stat().st_size / 1e6:.1f} MB): {verdict}")
        print(f"open it with: {rerun} {rrd}   (or watch live: cell up --rerun spawn | serve)")
    return rc


def _cmd_status(args: argparse.Namespace) -> int:
    from cell import launcher
    from cell.bus import BusError
    from cell.registry import format_status

    config = _load(args)
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
                )
            )
        )
    else:
        print(format_status(st))
    return 0 if all(s.health == "ok" for s in st.services) else 3


def _cmd_event(args: argparse.Namespace) -> int:
    """cell estop / stop / resume: one order on the Responsive Link, then the robots' reports."""
    from cell.rlink.client import EventClient

    config = _load(args)

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


def _cmd_config_show(args: argparse.Namespace) -> int:
    config = _load(args)
    print(f"# effective configuration: {config.source} over the embedded default\n")
    print(config.to_toml(), end="")
    return 0


def _report(args: argparse.Namespace, result: dict, text: str) -> int:
    """A benchmark's figures as text, then with --json as one JSON line, last."""
    print(text)
    if args.json:
        print(json.dumps(result))
    return 0


def _cmd_bench_bus(args: argparse.Namespace) -> int:
    from cell.bench import bus

    result = bus.run(messages=args.messages, pings=args.pings, rounds=args.rounds)
    return _report(args, result, bus.format_result(result))


def _cmd_bench_robots(args: argparse.Namespace) -> int:
    from cell.bench import robots

    backends = ["kinematic", "mujoco"] if args.backend == "all" else [args.backend]

    def log(trial: dict) -> None:
        print(robots.format_trial(trial), flush=True)

    result = robots.run_bench(backends, args.seconds, log=log, answer=not args.status_only)
    return _report(args, result, robots.format_result(result))


def _cmd_bench_dataplane(args: argparse.Namespace) -> int:
    from cell.bench import dataplane

    def log(trial: dict) -> None:
        print(dataplane.format_trial(trial), flush=True)

    if args.backend == "xdp":
        from cell.dataplane.xdp.switch import SwitchError

        try:
            result = dataplane.run_xdp(args.seconds, log=log)
        except SwitchError as exc:
            print(f"cell bench dataplane: {exc}", file=sys.stderr)
            return 2
        text = dataplane.format_xdp(result)
        if args.json:  # the figures first, flat (the trials follow in the full result)
            result = {**result.pop("summary"), **result}
        return _report(args, result, text)
    result = dataplane.run(args.seconds, log=log)
    return _report(args, result, dataplane.format_result(result))


def _cmd_bench_accuracy(args: argparse.Namespace) -> int:
    from cell.bench import accuracy

    result = accuracy.run(args.quick, log=lambda line: print(line, flush=True), backend=args.backend)
    result.pop("samples")
    return _report(args, result, accuracy.format_result(result))


def _cmd_bench_background(args: argparse.Namespace) -> int:
    from cell.bench import background

    result = background.run(
        args.quick, args.rate_mbps, args.buffer_ms, log=lambda line: print(line, flush=True)
    )
    return _report(
        args, background.summary(result) | {"rows": result["rows"]}, background.format_result(result)
    )


def _cmd_bench_paper(args: argparse.Namespace) -> int:
    import time

    from cell.bench import paper

    out = args.out or f"runs/paper-{time.strftime('%Y%m%d-%H%M%S')}"
    only = [x for x in args.only.split(",") if x] if args.only else None
    result = paper.run(args.quick, out, only, log=lambda line: print(line, flush=True))
    return _report(args, result, paper.format_result(result))


def _cmd_bench_skills(args: argparse.Namespace) -> int:
    import time

    from cell.bench import skills

    out = args.out or f"runs/skills-{time.strftime('%Y%m%d-%H%M%S')}"
    log = lambda line: print(line, flush=True)  # noqa: E731
    result = skills.run(args.messages, log=log, increments=args.increments, png_dir=out)
    return _report(args, result, skills.format_result(result))


def _cmd_bench_snp(args: argparse.Namespace) -> int:
    from cell.bench import snp

    native = {"auto": None, "c": True, "python": False}[args.cycle]
    management_ns = None if args.management_us is None else int(args.management_us * 1000)
    slot_ns = int(args.slot_us * 1000)
    result = snp.run(
        args.slaves, args.seconds, args.loss, slot_ns=slot_ns, native=native, management_ns=management_ns
    )
    return _report(args, result, snp.format_result(result))


def _cmd_bench_rlink(args: argparse.Namespace) -> int:
    import time

    from cell.bench import rlink

    png = args.png or f"runs/rlink-{time.strftime('%Y%m%d-%H%M%S')}.png"
    result = rlink.run(args.packets, png=png, estop_trials=args.estop_trials, estop_robots=args.estop_robots)
    return _report(args, result, rlink.format_result(result))


def _cmd_bench_bilateral(args: argparse.Namespace) -> int:
    import time

    from cell.teleop import experiment

    out = args.out or f"runs/bilateral-{time.strftime('%Y%m%d-%H%M%S')}"
    result = experiment.bench(out)
    return _report(args, result, experiment.format_result(result))


def _pushes(text: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected forces in N separated by commas (got {text!r})") from None
    if not out or any(not 0.5 < v <= 20 for v in out):
        raise argparse.ArgumentTypeError("each push aims at more than 0.5 N and at most 20 N")
    return out


def _cmd_teleop(args: argparse.Namespace) -> int:
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
        print(json.dumps(r))
    return 0


def _cmd_keys_generate(args: argparse.Namespace) -> int:
    from cell.bus import curve

    bad = [c for c in args.client if not c.replace("-", "").replace("_", "").isalnum() or c == curve.SERVER]
    if bad:
        print(
            f"error: bad client name {bad[0]!r} (letters, digits, - and _; not {curve.SERVER!r})",
            file=sys.stderr,
        )
        return 2
    written = curve.generate(args.dir, args.client)
    for path in written:
        print(path)
    print(f"{len(written)} file(s) in {args.dir}; the .key_secret files are private (mode 600)")
    return 0


def _cmd_chaos(args: argparse.Namespace) -> int:
    import asyncio

    from cell.chaos.campaign import campaign

    print(f"{'RD':>2} {'FAULT':<28} {'HELD?':<7} {'DETECT':>8} {'RECOVER':>8}  WHAT FAILED")
    result = asyncio.run(campaign(args.rounds, args.only, log_fn=lambda line: print(line, flush=True)))
    print(f"{result['held']} of {result['faults']} faults held every promise ({result['rounds']} round(s))")
    if args.json:
        print(json.dumps(result))
    return 0 if result["failed"] == 0 else 1


def _cmd_fuzz(args: argparse.Namespace) -> int:
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
        print(json.dumps(result))
    return 0 if result["ok"] else 1


def _bench(
    bsub: argparse._SubParsersAction, name: str, func: Callable[[argparse.Namespace], int], help: str
) -> argparse.ArgumentParser:
    """A `cell bench NAME` subcommand: its figures as text, with --json also as one JSON line, last."""
    q = bsub.add_parser(name, help=help)
    q.add_argument("--json", action="store_true", help="also print the result as one JSON line, last")
    q.set_defaults(func=func)
    return q


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cell",
        description="Run and inspect a networked industrial robot cell (README.md).",
    )
    parser.add_argument("--version", action="version", version=f"cell {__version__}")
    parser.add_argument(
        "--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"], help="default: INFO"
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("up", help="run the whole cell until Ctrl-C (or --duration)")
    _config_arg(p)
    p.add_argument("--duration", type=float, metavar="S", help="stop cleanly after S seconds")
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
    p.set_defaults(func=_cmd_up)

    p = sub.add_parser("demo", help="the main job: the default cell runs a bundled task, recorded for Rerun")
    _config_arg(p)
    p.add_argument("--out", metavar="PATH.rrd", help="where to record (default runs/<timestamp>.rrd)")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("run", help="run a task script's `async def main(cell)` against a running cell")
    p.add_argument("script", help="a Python file defining async def main(cell)")
    _config_arg(p)
    p.add_argument("--up", action="store_true", help="start the cell first (and stop it after)")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser(
        "service",
        help="run services in one process against a running bus",
        description="Runs the named services (built-in, e.g. robots, or [services.plugins] names) in "
        "one process, or with --group the services of a [[services.groups]] entry ('main': those no "
        "group names). The process takes the CPUs and priority of its group, as `cell up` gives them.",
    )
    p.add_argument("names", nargs="*", metavar="NAME", help="services to run")
    p.add_argument("--group", metavar="GROUP", help="run this process group's services instead")
    _config_arg(p)
    p.add_argument("--watch-stdin", action="store_true", help=argparse.SUPPRESS)  # set by `cell up`
    p.set_defaults(func=_cmd_service)

    p = sub.add_parser(
        "status",
        help="list a running cell's services, health, uptime and counters",
        description="Exit code: 0 every service ok, 1 no cell answered, 3 some service not ok.",
    )
    _config_arg(p)
    p.add_argument(
        "--timeout", type=float, default=2.0, metavar="S", help="give up after S seconds (default 2)"
    )
    p.add_argument("--json", action="store_true", help="print the status as JSON")
    p.set_defaults(func=_cmd_status)

    for name, what in (
        ("estop", "emergency stop over the Responsive Link: the drives brake at once"),
        ("stop", "stop over the Responsive Link on the data plane's ramp (the drives stay on)"),
        ("resume", "release robots stopped over the Responsive Link"),
    ):
        p = sub.add_parser(
            name,
            help=what,
            description=f"{what[0].upper()}{what[1:]}. Robots by name or id (none: every robot); "
            "waits until each reports (exit code 1 if one does not).",
        )
        p.add_argument("robots", nargs="*", metavar="ROBOT")
        _config_arg(p)
        p.add_argument("--no-wait", action="store_true", help="send the order and return")
        p.add_argument("--timeout", type=float, default=5.0, metavar="S", help="wait at most S (default 5)")
        p.set_defaults(func=_cmd_event)

    p = sub.add_parser(
        "teleop",
        help="bilateral teleoperation over the Responsive Link: an operator pushes an object through "
        "two arms, and feels it",
        description="Two MuJoCo arms, one process each, run the Fig. 14 force-reflecting servo at 1 ms over "
        "the Responsive Link (docs/teleop.md). A scripted operator pushes the object several times.",
    )
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
    p.add_argument("--json", action="store_true", help="also print the figures as one JSON line, last")
    p.set_defaults(func=_cmd_teleop)

    p = sub.add_parser(
        "chaos",
        help="fault campaign: the default cell in --processes mode, driven while faults hit it",
        description="Kills and hangs each service, takes the bus away, slows the controller's link, mutes a "
        "robot, then some at once, each mid-motion; prints per fault whether the cell's promises held, the "
        "time to detect and to recover (docs/faults.md). Exit code 0 only if every promise held.",
    )
    p.add_argument("--rounds", type=int, default=1, help="campaign rounds (default 1)")
    p.add_argument(
        "--only", nargs="+", metavar="TEXT", help="only the faults whose name contains one of these"
    )
    p.add_argument("--json", action="store_true", help="also print the figures as one JSON line, last")
    p.set_defaults(func=_cmd_chaos)

    p = sub.add_parser(
        "fuzz",
        help="bad input at scale: every listener of the default cell, then attacks on its resources",
        description="Sends --inputs generated inputs (hypothesis seeds of each wire format, mutated) to the "
        "skill servers, the data plane, SnP, the Responsive Link, the bus and the config loader, probing "
        "after every burst; then 10,000 idle TCP connections, a 1 byte/s client, a 100 MB line and a UDP "
        "flood. Exit code 0 only with no crash, no hang, every probe in its usual time and memory bounded.",
    )
    p.add_argument("--inputs", type=int, default=1_000_000, help="inputs per listener (default 10^6)")
    p.add_argument("--seed", type=int, default=1, help="the seed of every generator (default 1)")
    p.add_argument(
        "--only", nargs="+", metavar="TEXT", help="only the targets whose name contains one of these"
    )
    p.add_argument("--json", action="store_true", help="also print the figures as one JSON line, last")
    p.set_defaults(func=_cmd_fuzz)

    p = sub.add_parser("keys", help="CurveZMQ keys for a bus that leaves loopback")
    ksub = p.add_subparsers(dest="keys_command", required=True, metavar="ACTION")
    q = ksub.add_parser(
        "generate",
        help="the forwarder's certificate and one per client, each client allow-listed",
        description="Writes DIR/server.key(_secret), DIR/<client>.key(_secret) and DIR/allowed/<client>.key "
        "(cell/bus/curve.py). Existing certificates are kept: run it again to add clients. Then set "
        "[bus] curve = true, keys = DIR and client = NAME on every host.",
    )
    q.add_argument("--dir", default="keys", help="where (default: keys)")
    q.add_argument(
        "--client", nargs="+", default=["cell"], metavar="NAME", help="client names (default: cell)"
    )
    q.set_defaults(func=_cmd_keys_generate)

    p = sub.add_parser("config", help="inspect the configuration")
    csub = p.add_subparsers(dest="config_command", required=True, metavar="ACTION")
    q = csub.add_parser("show", help="print the effective configuration as TOML")
    _config_arg(q)
    q.set_defaults(func=_cmd_config_show)

    p = sub.add_parser("bench", help="measure hot paths next to a baseline in the same run")
    bsub = p.add_subparsers(dest="bench_command", required=True, metavar="TARGET")
    q = _bench(
        bsub,
        "bus",
        _cmd_bench_bus,
        "bus messages/s and round trip p50/p99 (64-byte payloads) next to raw pyzmq PUB/SUB",
    )
    q.add_argument("--messages", type=int, default=200_000, help="messages per throughput round")
    q.add_argument("--pings", type=int, default=2_000, help="round trips per latency round")
    q.add_argument("--rounds", type=int, default=3, help="alternating rounds of each (best is kept)")
    q = _bench(
        bsub,
        "robots",
        _cmd_bench_robots,
        "the most robots one core runs at 500 Hz status with < 0.1% late sends, per backend",
    )
    q.add_argument("--backend", choices=["kinematic", "mujoco", "all"], default="all")
    q.add_argument("--seconds", type=float, default=3.0, help="length of each trial (default 3)")
    q.add_argument(
        "--status-only", action="store_true", help="nobody answers the status (no command traffic)"
    )
    q = _bench(
        bsub,
        "dataplane",
        _cmd_bench_dataplane,
        "status/s answered within the command window, next to a bare reflector and a naive "
        "asyncio controller; latency at 10, 100, 300 robots",
    )
    q.add_argument("--seconds", type=float, default=2.0, help="length of each trial (default 2)")
    q.add_argument(
        "--backend",
        choices=["numpy", "xdp"],
        default="numpy",
        help="xdp: the XDP program in a switch namespace, next to a bare XDP reflector and numpy (root)",
    )
    q = _bench(
        bsub,
        "accuracy",
        _cmd_bench_accuracy,
        "MuJoCo arms driven through the data plane: stop error, tool path error, start shift",
    )
    q.add_argument("--quick", action="store_true", help="fewer reference motions (under 4 minutes)")
    q.add_argument("--backend", choices=["numpy", "xdp"], default="numpy", help="the data plane (xdp: root)")
    q = _bench(
        bsub,
        "background",
        _cmd_bench_background,
        "robot traffic beside ordinary traffic at a congested egress port of the data plane, one shared "
        "FIFO against strict priority, in network namespaces (NSDI'22 Appendix C, Fig. 14; needs root)",
    )
    q.add_argument("--quick", action="store_true", help="three load levels, 1 s each (about 50 s)")
    q.add_argument("--rate-mbps", type=float, default=100.0, help="the egress port's rate (default 100)")
    q.add_argument(
        "--buffer-ms", type=float, default=3.0, help="its buffer per queue, in ms of it (default 3)"
    )
    q = _bench(
        bsub,
        "paper",
        _cmd_bench_paper,
        "the NSDI'22 paper's evaluation in one run: every experiment, our figures next to the paper's, "
        "written to DIR/index.html with plots",
    )
    q.add_argument("--quick", action="store_true", help="every experiment smaller (under 5 minutes)")
    q.add_argument("--out", help="where to write index.html and the plots (default runs/paper-<time>)")
    q.add_argument(
        "--only", help="comma-separated experiments: accuracy,pid,latency,background,resubmission,scaling"
    )
    q = _bench(
        bsub,
        "skills",
        _cmd_bench_skills,
        "skill-protocol acknowledgement round trip, send gaps and switching, next to TCP echo; the Adept "
        "paper's tau_r, switching and send gaps over ufloop's approach with the camera (Figs. 10-13)",
    )
    q.add_argument("--messages", type=int, default=2000, help="messages per figure (default 2000)")
    q.add_argument(
        "--increments",
        type=int,
        default=4,
        help="ufloop approach increments per (speed, delta_z) of the paper's sweep, with the camera "
        "(default 4; 0: skip)",
    )
    q.add_argument("--out", metavar="DIR", help="where the PNGs go (default runs/skills-<time>)")
    q = _bench(
        bsub,
        "snp",
        _cmd_bench_snp,
        "the SpW-SnP-MR modular robot: its 1 ms cycle over time-bounded queries and over RMAP, "
        "SnP-TSP clocks, plug and operate",
    )
    q.add_argument("--slaves", type=int, default=6, help="joint modules (default 6)")
    q.add_argument("--seconds", type=float, default=3.0, help="length of the main trials (default 3)")
    q.add_argument("--loss", type=float, default=0.02, help="share of datagrams lost in the loss trials")
    q.add_argument(
        "--slot-us",
        type=float,
        default=30.0,
        help="joint j's cycle starts j slots into the period (time slots; default 30; 0: all at once)",
    )
    q.add_argument(
        "--management-us",
        type=float,
        help="where in the period the master sends beacons and probes and the bench samples the "
        "clocks: its management slot, after the joints' exchanges (default: CycleConfig's)",
    )
    q.add_argument(
        "--cycle",
        "--modules",
        dest="cycle",
        choices=("auto", "c", "python"),
        default="auto",
        help="where the cycle's hot paths (the modules' and the master's) run: c (built with cc on first "
        "use), python, or auto (c if it builds)",
    )
    q = _bench(
        bsub,
        "rlink",
        _cmd_bench_rlink,
        "Responsive Link: event and data round trips between two nodes, unloaded and with the data "
        "link flooded (Table 1, Fig. 10 of the Responsive Processor paper)",
    )
    q.add_argument("--packets", type=int, default=10_000, help="round trips per figure (default 10000)")
    q.add_argument("--png", metavar="PATH", help="the histogram (default runs/rlink-<time>.png)")
    q.add_argument("--estop-trials", type=int, default=300, help="e-stops timed (default 300; 0: none)")
    q.add_argument(
        "--estop-robots",
        type=int,
        default=333,
        help="robots (x 6 joints x 500 Hz) loading the data plane meanwhile (default 333: 1M status/s)",
    )
    q = _bench(
        bsub,
        "bilateral",
        _cmd_bench_bilateral,
        "bilateral teleoperation: forces, transparency and the 1 ms loops on the sponge and the wood, the "
        "twin drive's ramp, delay and the e-stop (Responsive Processor paper, Figs. 12-17)",
    )
    q.add_argument("--out", metavar="DIR", help="where the PNGs go (default runs/bilateral-<time>)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=args.log_level,
        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        rc = args.func(args)
        if args.command in ("up", "service"):
            # skip interpreter teardown: everything is closed, and extension modules (ruckig's
            # nanobind) would print reference-leak reports at exit that are not ours to fix
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(rc)
        return rc
    except ConfigError as exc:
        print(f"cell: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    except KeyboardInterrupt:
        return 130
