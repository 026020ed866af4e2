"""Whole cells as real processes: `cell up`, `cell status`, signals, supervision."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import sys
import time

import pytest

from cell.bus import Bus
from cell.launcher import fetch_status
from cell.v1 import bus_pb2
from tests.conftest import cell_env, cell_overrides, free_port, run_cell, write_config

ECHO = {"echo": "tests.plugins:echo"}
SIDE = [{"name": "side", "services": ["echo"]}]  # layout "groups": echo in a process of its own
LAYOUTS = ["single", "groups", "each"]


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie is dead too (it only waits to be reaped)
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ", 1)[1][0] != "Z"
    except FileNotFoundError:
        return False


def can_bind(endpoint: str) -> bool:
    host, port = endpoint.removeprefix("tcp://").rsplit(":", 1)
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, int(port)))
        except OSError:
            return False
    return True


@pytest.mark.parametrize("layout", LAYOUTS)
async def test_bus_round_trip_with_services_in_other_processes(start_cell, layout: str) -> None:
    cell = await start_cell(run=["bus", "echo"], plugins=ECHO, layout=layout, groups=SIDE)
    async with Bus.connect(cell.config.bus, "tester") as bus:
        out = await bus.subscribe("test/out/")
        reply = await bus.request("echo", "echo", bus_pb2.BenchPayload(data=b"ping"), bus_pb2.BenchPayload)
        assert reply.data == b"ping"
        for i in range(100):
            bus.publish("test/in/n", bus_pb2.BenchPayload(data=str(i).encode()))
        got = []
        async with asyncio.timeout(10):
            while len(got) < 100:
                got += await out.recv_batch()
        assert [e.decode(bus_pb2.BenchPayload).data for e in got] == [str(i).encode() for i in range(100)]
        assert {e.source for e in got} == {"echo"}
        assert out.lost == 0
    status = await fetch_status(cell.config)
    assert status.mode == layout
    pids = {s.name: s.last.pid for s in status.services}
    process = {s.name: s.last.process for s in status.services}
    assert pids["bus"] != os.getpid()
    if layout == "single":
        assert pids["bus"] == pids["echo"] == cell.proc.pid
        assert process == {"bus": "main", "echo": "main"}
    else:
        assert len({pids["bus"], pids["echo"], cell.proc.pid}) == 3
        assert process == (
            {"bus": "main", "echo": "side"} if layout == "groups" else {"bus": "bus", "echo": "echo"}
        )


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
async def test_signal_stops_everything_within_2s(start_cell, layout: str, sig: int) -> None:
    cell = await start_cell(run=["bus", "echo"], plugins=ECHO, layout=layout, groups=SIDE)
    status = await fetch_status(cell.config)
    pids = {s.last.pid for s in status.services} | {cell.proc.pid}
    rc, took, out, err = cell.stop(sig)
    assert rc == 0, err
    assert took < 2.0, f"shutdown took {took:.2f} s"
    assert [p for p in pids if pid_alive(p)] == []
    assert can_bind(cell.config.bus.pub) and can_bind(cell.config.bus.sub)
    assert "bus" in out and "echo" in out  # the closing summary
    assert "Traceback" not in err


async def test_children_stop_when_the_launcher_is_killed(start_cell) -> None:
    cell = await start_cell(run=["bus", "echo"], plugins=ECHO, groups=SIDE)
    status = await fetch_status(cell.config)
    children = [s.last.pid for s in status.services]
    cell.proc.kill()  # no chance to clean up: the children must notice on their own
    cell.proc.communicate()
    deadline = time.monotonic() + 5
    while any(pid_alive(p) for p in children) and time.monotonic() < deadline:
        await asyncio.sleep(0.05)
    assert [p for p in children if pid_alive(p)] == []


BENCH = """
import asyncio
from cell import aio
from cell.cellproc import running_cell
from cell.launcher import fetch_status
async def main():
    async with running_cell({"services": {"run": ["bus"]}}, quiet=True) as config:
        st = await fetch_status(config)
        print(st.launcher_pid, *(s.last.pid for s in st.services), flush=True)
        await asyncio.Event().wait()
aio.run(main())
"""


def _sigint_as_at_a_terminal() -> None:
    """A process started in the background by a shell that has no job control ignores SIGINT, and so
    do its children: a job at a terminal has it at its default (Python's KeyboardInterrupt)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.parametrize("how", ["SIGTERM", "SIGKILL", "Ctrl-C"])
async def test_a_cell_a_benchmark_started_stops_when_the_benchmark_is_killed(how: str) -> None:
    """`cell bench ...` (cell.cellproc.running_cell) ended by a signal it cannot clean up after
    leaves no `cell up` behind it (one held the packet path's core and ports until killed by hand).
    A terminal's Ctrl-C (SIGINT to the foreground process group) stops the cell in order: it reaches
    the benchmark alone, which stops the cell with one SIGTERM (had the cell had the SIGINT too, the
    SIGTERM was its second signal: it exited at once and left a fleet bench's XDP switch behind)."""
    bench = await asyncio.create_subprocess_exec(
        sys.executable,
        "-c",
        BENCH,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env=cell_env(),
        start_new_session=True,  # (its own process group, as a terminal's foreground job ...
        preexec_fn=_sigint_as_at_a_terminal,  # (... and SIGINT not ignored, as under CI's runner)
    )
    assert bench.stdout is not None and bench.stderr is not None
    async with asyncio.timeout(60):
        line = await bench.stdout.readline()
    cell = [int(p) for p in line.split()]
    assert len(cell) == 2 and all(pid_alive(p) for p in cell), line
    if how == "Ctrl-C":
        os.killpg(bench.pid, signal.SIGINT)
    else:
        bench.send_signal(signal.Signals[how])
    async with asyncio.timeout(30):
        err = (await bench.stderr.read()).decode()
        await bench.wait()
    deadline = time.monotonic() + 10
    while any(pid_alive(p) for p in cell) and time.monotonic() < deadline:
        await asyncio.sleep(0.05)
    assert [p for p in cell if pid_alive(p)] == []
    if how == "Ctrl-C":
        assert "exiting now" not in err, err  # (the launcher's words on a second signal)


async def test_a_killed_process_is_restarted_and_counted_and_the_rest_runs_on(start_cell) -> None:
    cell = await start_cell(run=["bus", "echo"], plugins=ECHO, groups=SIDE, backoff_initial_s=0.05)
    before = {s.name: s.last.pid for s in (await fetch_status(cell.config)).services}
    os.kill(before["echo"], signal.SIGKILL)
    deadline = time.monotonic() + 15
    seen = []  # (health, whether the heartbeat is the dead process's)
    while time.monotonic() < deadline:
        status = {s.name: s for s in (await fetch_status(cell.config)).services}
        echo = status["echo"]
        seen.append((echo.health, echo.last.pid == before["echo"]))
        if echo.health == "ok" and echo.last.pid != before["echo"]:
            break
        await asyncio.sleep(0.05)
    # the dead process's last heartbeat is never shown as ok once the launcher saw it die
    ghost = [h for h, old in seen if old]
    assert "backoff" in ghost and "ok" not in ghost[ghost.index("backoff") :], seen
    assert echo.health == "ok" and echo.last.pid != before["echo"]
    assert echo.last.restarts == 1 and "exited with code -9" in echo.last.last_error
    assert status["bus"].last.pid == before["bus"] and status["bus"].last.restarts == 0
    async with Bus.connect(cell.config.bus, "tester") as bus:  # and it serves again
        reply = await bus.request("echo", "echo", bus_pb2.BenchPayload(data=b"again"), bus_pb2.BenchPayload)
    assert reply.data == b"again"


async def test_cell_status_command(start_cell) -> None:
    cell = await start_cell(run=["bus", "echo"], plugins=ECHO, groups=SIDE)

    table = run_cell("status", "--config", str(cell.path))
    assert table.returncode == 0, table.stderr
    assert table.stdout.splitlines()[0].startswith("cell 'default' (layout groups)")
    rows = {
        line.split()[0]: line.split() for line in table.stdout.splitlines()[2:] if not line.startswith(" ")
    }
    assert rows["bus"][1] == "ok" and rows["echo"][1] == "ok"
    assert rows["bus"][4] == "main" and rows["echo"][4] == "side"  # PROCESS
    assert int(rows["bus"][3]) != int(rows["echo"][3])
    assert "forwarder.messages_in=" in table.stdout

    js = run_cell("status", "--config", str(cell.path), "--json")
    assert js.returncode == 0
    data = json.loads(js.stdout)
    assert data["mode"] == "groups"
    by_name = {s["name"]: s for s in data["services"]}
    assert by_name["bus"]["last"]["counters"]["forwarder.messages_in"] > 0
    assert by_name["echo"]["last"]["state"] == "SERVICE_STATE_RUNNING"
    assert len(js.stdout.strip().splitlines()) == 1  # one line, for machines
    pretty = run_cell("status", "--config", str(cell.path), "--json", "--indent")
    assert pretty.returncode == 0 and pretty.stdout.startswith('{\n  "')  # and for people
    assert json.loads(pretty.stdout)["mode"] == "groups"
    assert by_name["echo"]["last"]["uptime_s"] > 0
    # every service reports its share of its process's event loop, and the process its CPU time
    assert by_name["echo"]["last"]["process"] == "side"
    assert by_name["echo"]["last"]["sched"].startswith("normal, cpu")
    for s in data["services"]:
        assert "busy_s" in s["last"]["counters"] and "process.cpu_s" in s["last"]["counters"], s


def test_cell_status_without_a_cell(tmp_path) -> None:
    path = write_config(
        tmp_path / "c.toml",
        {"bus": {"pub": f"tcp://127.0.0.1:{free_port()}", "sub": f"tcp://127.0.0.1:{free_port()}"}},
    )
    t0 = time.monotonic()
    result = run_cell("status", "--config", str(path), "--timeout", "0.5")
    assert result.returncode == 1
    assert "no cell answered" in result.stderr
    assert time.monotonic() - t0 < 10


@pytest.mark.parametrize("layout", ["single", "groups"])
async def test_failing_service_is_restarted_with_backoff(start_cell, layout: str) -> None:
    cell = await start_cell(
        run=["bus", "echo", "crasher"],
        plugins={**ECHO, "crasher": "tests.plugins:crasher"},
        layout=layout,
        wait_for={"bus", "echo"},
        backoff_initial_s=0.05,
        backoff_max_s=0.2,
    )
    deadline = time.monotonic() + 15
    crasher = None
    while time.monotonic() < deadline:
        status = await fetch_status(cell.config)
        crasher = next(s for s in status.services if s.name == "crasher")
        if crasher.last.restarts >= 3:
            break
        await asyncio.sleep(0.05)
    assert crasher is not None and crasher.last.restarts >= 3, crasher
    assert "deliberate failure" in crasher.last.last_error
    # the rest of the cell is unharmed
    healthy = {s.name for s in status.services if s.health == "ok"}
    assert {"bus", "echo"} <= healthy
    rc, _, _, err = cell.stop()
    assert rc == 0
    assert "Traceback" in err and "RuntimeError: deliberate failure" in err  # never a silent death


@pytest.mark.parametrize("layout", ["single", "groups"])
def test_failing_service_stops_the_cell_when_configured(tmp_path, layout: str) -> None:
    data = cell_overrides(
        run=["bus", "crasher"], plugins={"crasher": "tests.plugins:crasher"}, on_failure="stop"
    )
    path = write_config(tmp_path / "c.toml", data)
    result = run_cell("up", "--config", str(path), "--duration", "30", "--layout", layout)
    assert result.returncode == 1
    assert "service 'crasher' failed" in result.stderr
    assert "RuntimeError: deliberate failure" in result.stderr


def test_duration_stops_cleanly_with_a_summary(tmp_path) -> None:
    path = write_config(tmp_path / "c.toml", cell_overrides(run=["bus"]))
    t0 = time.monotonic()
    result = run_cell("up", "--config", str(path), "--duration", "1.5")
    assert result.returncode == 0, result.stderr
    assert 1.5 <= time.monotonic() - t0 < 8
    assert "is up in" in result.stderr
    lines = result.stdout.splitlines()
    assert lines[0].startswith("cell 'default' (layout groups)")
    assert lines[2].split()[:2] == ["bus", "ok"]


async def test_a_second_cell_up_on_the_same_bus_is_refused_before_it_starts_anything(start_cell) -> None:
    """It used to print 'cell is up', fail on the bound ports in hundreds of traceback lines, let its
    controller join the first cell's bus, and exit 0."""
    cell = await start_cell(run=["bus", "dataplane", "controller"])
    t0 = time.monotonic()
    second = await asyncio.to_thread(run_cell, "up", "--config", str(cell.path), "--duration", "30")
    assert second.returncode == 1 and time.monotonic() - t0 < 10, second.stderr[-2000:]
    (line,) = second.stderr.strip().splitlines()
    assert line.startswith(f"cell: cell 'default' is already running on {cell.config.bus.pub} (cell up pid ")
    assert f"pid {cell.proc.pid}, config {cell.path}" in line
    st = await fetch_status(cell.config)
    assert st.launcher_pid == cell.proc.pid  # the first cell's, untouched
    assert {s.name for s in st.services if s.health == "ok"} == {"bus", "dataplane", "controller"}
