"""`cell up`, `cell service` and `cell status`: start services, keep the status registry, stop cleanly."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import AsyncIterator
from dataclasses import replace
from pathlib import Path

from cell import sched
from cell.aio import stop_on_signals, stop_on_stdin_eof
from cell.bus import Bus, BusError, BusRefused, identity
from cell.config import CellConfig, parse_host_port
from cell.dataplane.xdp.switch import SwitchError, switch_namespace
from cell.layout import Process, process_for, process_named, processes
from cell.processes import ChildProcess
from cell.service import load_all
from cell.status import Health, StatusRegistry, format_status, status_names
from cell.supervisor import ServiceFailed, Supervisor
from cell.v1 import health_pb2

log = logging.getLogger("cell")


async def up(
    config: CellConfig,
    *,
    duration: float | None = None,
    log_level: str = "INFO",
    counters: bool = False,
    watch_stdin: bool = False,
) -> int:
    """Run the cell until SIGINT/SIGTERM or `duration` (or, watch_stdin, its standard input's end:
    the parent that started it is gone); print a summary; 0 on a clean stop.

    The services go into processes as `[services] layout` says (cell/layout.py); the
    launcher itself keeps the status registry and, in the "single" layout, runs everything.
    """
    running = await already_running(config)
    if running:
        print(f"cell: {running}", file=sys.stderr)
        return 1
    await _join(config)
    with contextlib.ExitStack() as stack:
        if config.dataplane.runs.in_kernel:
            try:
                stack.enter_context(switch_namespace(config.dataplane.switch))
            except SwitchError as exc:
                print(f"cell: {exc}", file=sys.stderr)
                return 2
        return await _up(
            config, duration=duration, log_level=log_level, counters=counters, watch_stdin=watch_stdin
        )


async def _join(config: CellConfig) -> None:
    """Make this start's processes members of their cell on its bus (cell/bus/identity.py): a new
    start where the bus runs; on another host of the cell, the start of the one running there."""
    if "bus" in config.services.run:
        identity.new_start()
        return
    try:
        st = await fetch_status(config, timeout=config.bus.connect_timeout_s)
    except BusError:  # (not up yet: this host's services join as the cell's clients do)
        log.warning(
            "no cell %r answered on its bus yet: this host joins it without a start", config.cell.name
        )
        return
    identity.join(st.member)


async def already_running(config: CellConfig) -> str:
    """Why this cell cannot start here ("" if it can): its bus address is taken, by a running cell
    (which one, where, started how) or by another program.  Checked before anything starts, so that a
    second `cell up` never half-starts and joins the first one's bus."""
    if "bus" not in config.services.run or not config.bus.pub.startswith("tcp://"):
        return ""
    host, port = parse_host_port(config.bus.pub.removeprefix("tcp://"))
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # (a port in TIME_WAIT is free)
        try:
            s.bind((host, port))
            return ""
        except OSError:
            pass
    try:
        st = await fetch_status(config, timeout=2.0)
    except BusRefused:
        return (
            f"the bus address {config.bus.pub} is taken by another cell's bus (not {config.cell.name!r}'s): "
            "stop it, or set [bus] pub"
        )
    except BusError:
        return f"the bus address {config.bus.pub} is taken by another program: free it or set [bus] pub"
    return (
        f"cell {st.cell!r} is already running on {config.bus.pub} (cell up pid {st.launcher_pid}, config "
        f"{st.config or '?'}, up {st.uptime_s:.0f} s): stop it first (Ctrl-C there, or kill it)"
    )


async def _up(
    config: CellConfig, *, duration: float | None, log_level: str, counters: bool, watch_stdin: bool
) -> int:
    layout = config.services.layout
    registry = StatusRegistry.of(config)
    stop = asyncio.Event()
    t0 = time.monotonic()
    final: health_pb2.CellStatus | None = None
    failed: Exception | None = None  # (a ServiceFailed, or a group of them)
    with stop_on_signals(stop), tempfile.TemporaryDirectory(prefix="cell-") as tmp:
        timer = asyncio.get_running_loop().call_later(duration, stop.set) if duration else None
        watch = await stop_on_stdin_eof(stop) if watch_stdin else None
        try:
            async with asyncio.TaskGroup() as tg:
                if layout == "single":
                    tg.create_task(Supervisor(config, load_all(config)).run(stop), name="supervisor")
                else:
                    children = processes(config)
                    log.info("layout %s: %s", layout, "; ".join(map(_describe, children)))
                    # the children read the effective config (command-line changes included)
                    effective = Path(tmp) / "cell.toml"
                    effective.write_text(config.to_toml())
                    for p in children:
                        child = ChildProcess(
                            p,
                            config,
                            effective,
                            group=layout == "groups",
                            log_level=log_level,
                            on_restart=registry.process_restarted,
                        )
                        tg.create_task(child.run(stop), name=f"process:{p.name}")
                keeper = tg.create_task(_keep_registry(config, registry, t0), name="registry")
                await stop.wait()
                final = registry.status()
                keeper.cancel()
        except* ServiceFailed as group:
            failed = group.exceptions[0]
        finally:
            if timer is not None:
                timer.cancel()
            if watch is not None:
                watch.close()
    if failed is not None:
        print(f"cell: {failed}; the cell stopped (services.on_failure = 'stop')", file=sys.stderr)
        return 1
    log.info("cell %r stopped after %.1f s", config.cell.name, time.monotonic() - t0)
    if final is not None:  # (the counters with --verbose, or from `cell status` while it runs)
        print(format_status(final, counters=counters))
    return 0


def _describe(p: Process) -> str:
    how = [f"cpus {','.join(map(str, p.cpus))}"] if p.cpus else []
    how += [f"SCHED_FIFO {p.rt_priority}"] if p.rt_priority else []
    return f"{p.name} ({', '.join(p.services)}{''.join('; ' + h for h in how)})"


async def _keep_registry(config: CellConfig, registry: StatusRegistry, t0: float) -> None:
    announced = False
    mine = set(status_names(config))
    while True:
        try:
            async with Bus.connect(config.bus, "cell") as bus:
                reader = asyncio.ensure_future(registry.run(bus))
                try:
                    while not announced and not reader.done():
                        if all(s.health == Health.OK for s in registry.status().services if s.name in mine):
                            announced = True
                            log.info(
                                "cell %r is up in %.2f s (%s): `cell status` to inspect, Ctrl-C to stop",
                                config.cell.name,
                                time.monotonic() - t0,
                                ", ".join(sorted(mine)),
                            )
                            break
                        await asyncio.wait([reader], timeout=0.05)
                    await reader
                finally:
                    reader.cancel()
        except BusError as exc:
            log.warning("status registry waiting for the bus: %s", exc)
            await asyncio.sleep(0.5)


async def service(
    config: CellConfig, names: list[str] | None = None, *, group: str | None = None, watch_stdin: bool = False
) -> int:
    """Run services in this process (the named ones, or process group `group`'s) until SIGINT/SIGTERM,
    placed on the CPUs and at the priority their group asks for, before anything else starts."""
    process = process_named(config, group) if group is not None else process_for(config, names or [])
    for problem in sched.place_loops(process.cpus, process.rt_priority, process.nice):
        log.warning("process %r: %s", process.name, problem)
    config = process.config_for(config)
    specs = load_all(config, process.services)
    sched.settle_heap()  # (the services' modules loaded: they live as long as the process)
    stop = asyncio.Event()
    with stop_on_signals(stop):
        watch = await stop_on_stdin_eof(stop) if watch_stdin else None
        try:
            node = f"supervisor-{process.name}-{os.getpid()}"
            await Supervisor(config, specs, node_name=node, process=process.name).run(stop)
        except ServiceFailed as exc:
            print(f"cell: {exc}", file=sys.stderr)
            return 1
        finally:
            if watch is not None:
                watch.close()
    return 0


async def fetch_status(config: CellConfig, timeout: float = 2.0) -> health_pb2.CellStatus:
    """Ask a running cell for its status; BusUnavailable/BusTimeout if none answers."""
    bus_cfg = replace(config.bus, connect_timeout_s=timeout)
    async with Bus.connect(bus_cfg, f"status-{os.getpid()}") as bus:
        reply = await bus.request(
            "cell", "status", health_pb2.StatusRequest(), health_pb2.CellStatus, timeout
        )
    assert isinstance(reply, health_pb2.CellStatus)
    return reply


ASK_S = 0.25  # a status request unanswered this long is asked again (see wait_healthy)


async def wait_healthy(
    config: CellConfig,
    want: set[str],
    timeout: float = 60.0,
    proc: asyncio.subprocess.Process | subprocess.Popen | None = None,
) -> health_pb2.CellStatus:
    """Until every service in `want` is ok; the status that said so.  One bus connection, asked
    again every ASK_S: a request sent before the launcher serves cell.status (it subscribes after
    the forwarder is up) is lost, and waiting out a long timeout on it cost each start a second.
    TimeoutError (naming the services not ok yet) after `timeout`; RuntimeError if proc exits."""
    last: health_pb2.CellStatus | None = None
    bus_cfg = replace(config.bus, connect_timeout_s=timeout)
    try:
        async with asyncio.timeout(timeout), Bus.connect(bus_cfg, f"status-{os.getpid()}") as bus:
            while True:
                with contextlib.suppress(BusError):
                    reply = await bus.request(
                        "cell", "status", health_pb2.StatusRequest(), health_pb2.CellStatus, ASK_S
                    )
                    assert isinstance(reply, health_pb2.CellStatus)
                    last = reply
                    if want <= {s.name for s in last.services if s.health == Health.OK}:
                        return last
                code = (
                    proc.poll() if isinstance(proc, subprocess.Popen) else getattr(proc, "returncode", None)
                )
                if code is not None:
                    raise RuntimeError(f"the cell exited with code {code}")
                await asyncio.sleep(0.05)  # (the next heartbeat comes by itself: no busy asking)
    except (TimeoutError, BusError):
        ok = set() if last is None else {s.name for s in last.services if s.health == Health.OK}
        raise TimeoutError(
            f"services {sorted(want - ok)} not ok within {timeout:g} s (last status: {last})"
        ) from None


@contextlib.asynccontextmanager
async def child_cell(
    config_path: Path | None, config: CellConfig, quiet: bool = False
) -> AsyncIterator[None]:
    """`cell up` in a child process, healthy when the block starts, stopped when it ends (for
    `cell run --up`, `cell demo` and benchmarks); quiet: without its summary at the stop."""
    # (--watch-stdin: the cell stops when this process ends, however it ends: SIGTERM or SIGKILL
    # leave no cell running behind a benchmark.  A session of its own: a terminal's Ctrl-C reaches
    # this process, which stops the cell with one SIGTERM; had the cell had the SIGINT too, that
    # SIGTERM was its second signal, on which it exits at once, leaving its XDP switch behind)
    cmd = [sys.executable, "-m", "cell", "--log-level", "WARNING", "up", "--watch-stdin"]
    if config_path is not None:
        cmd += ["--config", str(config_path)]
    if config.cell.host:
        cmd += ["--host", config.cell.host]
    out = subprocess.DEVNULL if quiet else None
    proc = await asyncio.create_subprocess_exec(
        *cmd, stdin=subprocess.PIPE, stdout=out, env=dict(os.environ), start_new_session=True
    )
    try:
        await wait_healthy(config, set(status_names(config)), 60.0, proc)
        yield
    finally:
        if proc.returncode is None:
            proc.send_signal(signal.SIGTERM)
            try:
                async with asyncio.timeout(10):
                    await proc.wait()
            except TimeoutError:
                proc.kill()
                await proc.wait()
