"""Where services run: the layouts' processes, CPU pinning and real-time priority, the event-loop meter."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import time

import pytest

from cell import meter
from cell.config import ConfigError, load_config
from cell.layout import process_for, process_named, processes
from tests.conftest import cell_env

RUN = ["bus", "dataplane", "robots", "controller", "recorder"]


def config(layout: str, **services: object):
    return load_config(overrides={"services": {"run": RUN, "layout": layout, **services}})


def test_groups_put_the_packet_path_in_processes_of_its_own() -> None:
    got = {p.name: (p.services, p.cpus, p.rt_priority) for p in processes(config("groups"))}
    assert got == {
        "main": (["bus", "controller", "recorder"], [], 0),
        "robots": (["robots"], [1], 70),
        "dataplane": (["dataplane"], [1], 60),
    }
    assert processes(config("groups"))[0].name == "main"  # started first: it has the bus


def test_single_and_each() -> None:
    (only,) = processes(config("single"))
    assert (only.name, only.services, only.rt_priority) == ("main", RUN, 0)
    each = {p.name: (p.services, p.rt_priority) for p in processes(config("each"))}
    assert each["robots"] == (["robots"], 70)  # a service in a group keeps its scheduling
    assert each["controller"] == (["controller"], 0)
    assert list(each) == RUN
    # ... but for its real-time priority, which is its native loop's: the hub alone runs no such loop
    hub = load_config(overrides={"services": {"layout": "each", "run": ["bus", "robots", "rlink"]}})
    rlink = {p.name: p for p in processes(hub)}["rlink"]
    assert (rlink.rt_priority, rlink.cpus, rlink.nice) == (0, [1], -10)


def test_a_group_with_nothing_to_run_starts_no_process() -> None:
    cfg = load_config(overrides={"services": {"run": ["bus", "controller"]}})
    assert [p.name for p in processes(cfg)] == ["main"]


def test_cell_service_places_a_service_as_cell_up_would() -> None:
    cfg = config("groups")
    assert process_for(cfg, ["robots"]).rt_priority == 70
    assert process_for(cfg, ["controller"]).rt_priority == 0
    assert process_for(cfg, ["robots", "controller"]).rt_priority == 0  # no common group
    assert process_named(cfg, "main").services == ["bus", "controller", "recorder"]
    with pytest.raises(ConfigError, match="no process group 'gpu'"):
        process_named(cfg, "gpu")


PLACE = """
import json, os, sys
from cell import sched
if sys.argv[1] == "nobody":
    os.setgid(65534); os.setuid(65534)  # no CAP_SYS_NICE, RLIMIT_RTPRIO 0: real time is refused
if os.cpu_count() > 1:
    os.sched_setaffinity(0, {1})  # a parent's narrower mask does not stop the process moving to CPU 0
problems = sched.place([0, 99], 10, -5)
print(json.dumps({"problems": problems, "now": sched.describe()}))
"""


def place_in_child(user: str) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", PLACE, user], capture_output=True, text=True, env=cell_env(), timeout=30
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


@pytest.mark.skipif(os.geteuid() != 0, reason="granting SCHED_FIFO needs root or CAP_SYS_NICE")
def test_a_process_is_pinned_and_made_real_time_where_allowed() -> None:
    got = place_in_child("root")
    assert got["now"] == "fifo 10, cpu 0"
    assert got["problems"] == ["CPUs [99] do not exist here: pinned to [0]"]


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to become an unprivileged user")
def test_where_real_time_is_refused_the_process_says_so_and_runs_on() -> None:
    got = place_in_child("nobody")
    assert got["now"] == "normal, cpu 0"
    assert any("SCHED_FIFO 10 refused" in p for p in got["problems"]), got
    assert any("nice -5 refused" in p for p in got["problems"]), got


PLACE_LOOPS = """
import json, os, socket
from cell import sched
from cell.dataplane.native import NativeProgram, NativeServer
def policies():
    return {int(t): os.sched_getscheduler(int(t)) & 0xFF for t in os.listdir("/proc/self/task")}
problems = sched.place_loops([0], 10, -5)
started = policies()  # (the group's Python, from its first import on)
sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
sock.bind(("127.0.0.1", 0))
server = NativeServer(NativeProgram(8, 8, 6), sock)
server.start(sched.LOOP_PRIORITY)
tid = int(server.state.tid)
loop_policy = os.sched_getscheduler(tid) & 0xFF  # (before any hand_over: from its first instruction)
problems += sched.hand_over(tid)
now, described = policies(), sched.describe()
problems += sched.rest_at(50)  # (a Python loop that must be real-time: under the native one)
from cell import rtbudget
watcher = rtbudget.watcher()  # (the rest's budget: at the loops' priority, over the rest)
raised = {t: os.sched_getparam(t).sched_priority for t in policies() if t not in (tid, watcher)}
watching = os.sched_getparam(watcher).sched_priority if watcher else 0
server.stop()
print(json.dumps({"problems": problems, "started": list(started.values()), "loop": loop_policy,
                  "rest": [p for t, p in now.items() if t != tid], "now": described,
                  "raised": list(raised.values()), "watcher": watching}))
"""


@pytest.mark.skipif(os.geteuid() != 0, reason="granting SCHED_FIFO needs root or CAP_SYS_NICE")
def test_a_real_time_group_runs_its_native_loop_alone_at_its_priority_from_its_start() -> None:
    """A group's Python (imports, models) never runs at SCHED_FIFO: starting up at FIFO 70 on the
    packet path's core, the robots' process held the data plane's loop there for up to 340 ms."""
    out = subprocess.run(
        [sys.executable, "-c", PLACE_LOOPS], capture_output=True, text=True, env=cell_env(), timeout=60
    )
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout)
    assert got["problems"] == []
    assert set(got["started"]) == {os.SCHED_OTHER}
    assert got["loop"] == os.SCHED_FIFO
    assert set(got["rest"]) == {os.SCHED_OTHER}
    assert got["now"].startswith("fifo 10 native, rest nice -10, cpu 0"), got["now"]
    assert set(got["raised"]) == {9}  # (rest_at: capped under the loop's 10)
    assert got["watcher"] == 10  # (and its budget's watcher, cell.rtbudget, at the loop's priority)


def test_a_benchmarks_client_process_that_dies_is_reported_at_once_not_at_its_timeout() -> None:
    from cell.bench.ur import _in_process
    from tests.plugins import dies, doubles

    assert _in_process(doubles, 21, timeout=60) == 42
    t0 = time.monotonic()
    with pytest.raises(RuntimeError, match=r"dies ended \(exit code 3\) with no result"):
        _in_process(dies, 21, timeout=60)
    assert time.monotonic() - t0 < 30  # (not the 60 s timeout: within the child's start and a poll)


def test_a_benchmark_run_in_process_gives_the_process_its_cpus_back() -> None:
    from cell.bench import pinned

    before = os.sched_getaffinity(0)
    with pinned(0):
        assert os.sched_getaffinity(0) == {0}
    assert os.sched_getaffinity(0) == before


SETTLE = """
import gc, json, time
import numpy
from cell import sched
import cell.snp.modular, cell.dataplane.pipeline
def full_pass_walks():
    gc.collect()  # (anything young is now old)
    return len(gc.get_objects(generation=2))
before = full_pass_walks()
sched.settle_heap()
made = [[i] for i in range(100)]  # what a loop makes after start-up is still collected
print(json.dumps({"before": before, "after": full_pass_walks(), "frozen": gc.get_freeze_count()}))
"""


def test_a_settled_heap_leaves_only_new_objects_to_the_garbage_collectors_full_pass() -> None:
    out = subprocess.run(
        [sys.executable, "-c", SETTLE], capture_output=True, text=True, env=cell_env(), timeout=60
    )
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout)
    assert got["before"] > 10_000  # numpy and the cell's modules: what a full pass walked
    assert got["frozen"] >= got["before"] - 100
    assert 100 <= got["after"] < 1_000  # the loop's own lists, not start-up's


async def test_the_meter_charges_each_service_its_own_loop_time() -> None:
    meter.install(asyncio.get_running_loop())

    async def spin(ms: float) -> None:
        t = time.perf_counter()
        while time.perf_counter() - t < ms / 1e3:
            pass

    async def service(account: meter.Account, ms: float) -> int:
        meter.charge_to(account)
        async with asyncio.TaskGroup() as tg:  # child tasks charge the same account
            for _ in range(3):
                tg.create_task(spin(ms))
        await asyncio.sleep(0.001)
        return 7

    light, heavy = meter.Account("light"), meter.Account("heavy")
    results = await asyncio.gather(
        asyncio.create_task(service(light, 5)), asyncio.create_task(service(heavy, 20))
    )
    assert results == [7, 7]
    # at least the spinning; at most that plus room for this VM's stalls (spins count wall time)
    assert 15e6 <= light.busy_ns < 45e6
    assert 60e6 <= heavy.busy_ns < 130e6
    task = asyncio.create_task(asyncio.sleep(10))  # cancellation goes through the wrapper
    await asyncio.sleep(0)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task


def test_a_rate_needs_a_whole_window() -> None:
    rate = meter.Rate(1.0)
    assert rate.update(0.0, now=10.0) is None
    assert rate.update(50.0, now=10.5) is None  # too soon: no rate from half a window
    assert rate.update(200.0, now=12.0) == pytest.approx(100.0)
    assert rate.update(300.0, now=12.2) == pytest.approx(100.0)  # the last window's, until the next
