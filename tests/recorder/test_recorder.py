"""The recorder writes real Rerun recordings, read back with Rerun's own reader; `cell demo` end to end."""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import subprocess
import sys
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import rtde_io
from rerun.chunk import RrdReader

from cell.bus import Bus
from cell.controller.controller import Controller
from cell.dataplane.client import DataplaneClient
from cell.launcher import fetch_status
from cell.rlink.client import EventClient
from cell.v1 import controller_pb2, robot_pb2
from tests.conftest import cell_env, cell_overrides, free_port, run_cell, write_config

Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])


def cell_times(path: Path, entity: str) -> np.ndarray:
    """The `cell_time` (ns) of every row logged to one entity."""
    times: list[int] = []
    for chunk in RrdReader(path).stream():
        if str(chunk.entity_path) == entity:
            times += chunk.to_record_batch().column("cell_time").cast(pa.int64()).to_pylist()
    return np.array(times, dtype=np.int64)


def rows_by_entity(path: Path) -> Counter[str]:
    rows: Counter[str] = Counter()
    for chunk in RrdReader(path).stream():
        rows[str(chunk.entity_path)] += chunk.num_rows
    return rows


@contextlib.asynccontextmanager
async def saving_cell(tmp_path: Path, robots: list[dict], services: list[str], rrd: Path):
    """`cell up` with the recorder saving to rrd, healthy, once the data plane has heard every robot;
    (bus, the cell's config).  The cell is stopped (cleanly: the recording is closed) when the block
    ends.  A test drives the cell's own controller service when it runs one: a second controller on
    the same data plane would take its robots over (each flushes what it finds in the tables as it
    starts, and stops robots moving on them: a CI run's robots stood still at 76 % of a move when the
    cell's controller came up late, in the middle of it)."""
    from cell.config import load_config
    from tests.conftest import wait_status

    data = cell_overrides(robots, run=services)
    data["recorder"] = {"mode": "save", "path": str(rrd), "hz": 30.0}
    cfg_path = write_config(tmp_path / f"{rrd.stem}.toml", data)
    proc = subprocess.Popen(
        [sys.executable, "-m", "cell", "up", "--config", str(cfg_path)],
        env=cell_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        config = load_config(cfg_path)
        await wait_status(config, set(services))
        async with Bus.connect(config.bus, "test") as bus:
            dp, ids = DataplaneClient(bus), {r["id"] for r in robots}
            async with asyncio.timeout(10):
                while {r.robot_id for r in (await dp.state(robots_only=True)).robots if r.status_ns} != ids:
                    await asyncio.sleep(0.05)
            yield bus, config
    finally:
        proc.terminate()
        proc.communicate(timeout=20)
    assert proc.returncode == 0


async def test_a_recording_holds_both_robots_their_series_and_the_data_plane(start_cell, tmp_path) -> None:
    rrd = tmp_path / "run.rrd"
    robots = [
        {"id": i, "name": f"r{i}", "skill_port": free_port(), "backend": "kinematic", "truth_hz": 100}
        for i in (1, 2)
    ]
    services = ["bus", "dataplane", "robots", "rlink", "controller", "recorder"]
    cell = await start_cell(run=services, robots=robots)  # recorder off by the default config ...
    code, _, _, _ = cell.stop()
    assert code == 0
    # ... so start one that saves
    async with saving_cell(tmp_path, robots, services, rrd) as (bus, config):
        M = controller_pb2.MoveRequest  # (as a user's script moves them: the cell's controller)
        moves = [
            M(robot=n, kind=M.JOINTS, values=(Q0 + d).tolist(), speed=80)
            for n, d in (("r1", 0.2), ("r2", -0.2))
        ]
        together = controller_pb2.MoveTogetherRequest(moves=moves)
        await bus.request("controller", "move_together", together, controller_pb2.MoveReply, 20.0)
        async with EventClient(config) as link:  # an e-stop and a release, for the event log
            await link.estop(["r2"])
            await link.resume(["r2"])
        # a digital output set and cleared by UR's own IO client, as a gripper would be, each shown
        events = await bus.subscribe("events/robot/r1")
        io = await asyncio.to_thread(rtde_io.RTDEIOInterface, config.robots[0].ur_host)
        try:
            for on in (True, False):
                assert io.setStandardDigitalOut(3, on)
                async with asyncio.timeout(5):
                    while True:
                        e = (await events.recv()).decode(robot_pb2.RobotEvent)
                        if e.kind == robot_pb2.RobotEvent.KIND_OUTPUTS:
                            break
                assert (e.text, e.digital_out) == (("DO3 on", 8) if on else ("DO3 off", 0))
        finally:
            io.disconnect()
        busy = next(s for s in (await fetch_status(config)).services if s.name == "recorder").last.counters
    # the recorder's own loop time stays well under a core; it is wall time, which a loaded
    # 2-core machine stretches (250-320 ms/s seen in a full test run), so the bound is loose and
    # the drawing rate is checked exactly below
    assert 0 < busy["busy_ms_per_s"] < 500, dict(busy)
    rows = rows_by_entity(rrd)
    for name in ("r1", "r2"):
        links = [e for e in rows if e.startswith(f"/robots/{name}/links/") and not e.endswith("/geom")]
        assert len(links) == 6, links  # a pose per link
        assert min(rows[e] for e in links) > 20  # drawn over and over
        # ... at [recorder] hz = 30 at most on the cell's timeline, although the truth comes at 100 Hz
        gaps = np.diff(np.sort(cell_times(rrd, links[0])))
        assert gaps.min() >= 1e9 / 30 - 1e6, gaps / 1e6
        # the tool path (a line of hundreds of points) is redrawn a few times a second, not every time
        assert 5 < rows[f"/robots/{name}/tool_path"] < min(rows[e] for e in links) / 3
        assert rows[f"/robots/{name}/tps"] >= 1  # the plan's points
        for series in (
            "position/j1/actual",
            "position/j1/planned",
            "velocity/j6/commanded",
            "tracking_error/j3",
        ):
            assert rows[f"/joints/{name}/{series}"] > 5, series
    assert all(rows[f"/services/{s}/restarts"] >= 1 for s in ("dataplane", "robots", "controller"))
    assert rows["/dataplane/answer_p99_us"] >= 1 and rows["/events"] >= 4  # joins, e-stop, still, release
    assert rows["/robots/r1/io/DO3"] == 2 and "/robots/r2/io/DO3" not in rows  # on, then off
    for node in ("dataplane", "robots", "rlink"):  # every node's links, from the heartbeats (1/s at most)
        assert (
            rows[f"/rlink/{node}/L1/event/packets_in"] >= 1
            and rows[f"/rlink/{node}/L1/event/packets_out"] >= 1
        )
        assert rows[f"/rlink/{node}/drops/crc"] >= 1
    rerun = Path(sys.executable).parent / "rerun"
    check = subprocess.run(
        [str(rerun), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120
    )
    assert check.returncode == 0, check.stderr
    # the view comes laid out for the cell (cell.recorder.blueprint): the blueprint is in the file,
    # its views named after the cell's robots
    printed = subprocess.run(
        [str(rerun), "rrd", "print", "-vvv", str(rrd)], capture_output=True, text=True, timeout=120
    ).stdout
    for view in (
        "r1: joint position (rad)",
        "r2: velocity and command (rad/s)",
        "data plane: status -> command",
    ):
        assert view in printed, view


@pytest.mark.slow
def test_cell_demo_runs_the_main_job_end_to_end(tmp_path) -> None:
    cfg = write_config(tmp_path / "cell.toml", cell_overrides())
    out, bag = tmp_path / "demo.rrd", tmp_path / "demo-bag"
    proc = subprocess.run(
        [sys.executable, "-m", "cell", "demo", "--config", str(cfg), "--out", str(out), "--bag", str(bag)],
        env=cell_env(),
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    text = proc.stdout
    for line in ("moves done", "tool path error at TPs", "SnP queries answered", "verified", "real time"):
        assert line in text, text[-3000:]
    assert "NOT verified" not in text
    # a verdict where there is an aim, the worst TP named, which data plane ran and why; the counters
    # left to `cell status` (or `cell up --verbose`)
    worst = re.search(r"tool path error at TPs, max / median\s+([✓✗]) .*worst: (r[12]), plan (\d+)", text)
    assert worst is not None, text[-3000:]
    assert re.search(r"data plane\s+(numpy|native|xdp) \(", text) and re.search(r"stop error .*\s[✓✗] ", text)
    assert "forwarder.messages_in=" not in text and "bus.published=" not in text
    # the default cell keeps real time under the demo's load: the robots (the ground truth of every
    # figure) miss fewer than 0.5% of their 2 ms ticks (aim 0.1%; single-process missed 15-30%)
    got = re.search(r"robot ticks missed / late sends\s+([\d,]+) of ([\d,]+)", text)
    assert got is not None, text[-3000:]
    missed, periods = (int(g.replace(",", "")) for g in got.groups())
    assert periods > 8_000  # the whole demo at 500 Hz
    # ... but for what the hypervisor took of the packet path's CPU (steal: a run stolen 8% of CPU 1
    # missed 3.06%, one stolen 0.1% missed 0.01%)
    stolen = re.search(r"hypervisor steal, packet path's CPU\s+CPU \d+: \d+ ms \(([\d.]+)% of the", text)
    assert stolen is not None, text[-3000:]
    assert missed / periods < 0.005 + float(stolen.group(1)) / 100, text[-3000:]
    lost = re.search(r"lost to Python \(ring overruns\) / bus messages lost\s+([\d,]+) / ([\d,]+)", text)
    assert lost is not None, text[-3000:]  # (what the bag's joint states below may miss, said)
    overruns = int(lost.group(1).replace(",", ""))
    placed = re.search(r"processes \(groups\)\s+(.*)", text)
    assert placed is not None and "robots: " in placed.group(1), text[-3000:]
    if os.geteuid() == 0:  # SCHED_FIFO is granted (elsewhere the cell says what it got instead)
        # (the tick in C's thread at SCHED_FIFO 70, the rest of the process at the normal policy)
        assert "robots: fifo 70 native, rest nice -10, cpu 1" in placed.group(1)
    rows = rows_by_entity(out)
    assert any(e.startswith("/skills/r1/busy") for e in rows) and any(
        e.startswith("/skills/r2/busy") for e in rows
    )
    # the same run as a ROS 2 bag, read back with rosbags: every robot's joint states at its full 500 Hz
    # over the run, the plans the controller loaded, the demo's events on /rosout.  Every tick the
    # robots ran is there: a missed tick (the robots' CPU stolen) steps over its periods and leaves
    # none, so the rate is 500 Hz less the ticks missed (a CI run stolen 10% of CPU 1: 481 Hz)
    from cell.recorder.bag import info

    b = info(bag)
    topics = {t.topic: t for t in b.topics}
    ran_hz = 500 * (periods - missed - overruns) / periods
    for robot in ("r1", "r2"):
        js = topics[f"/{robot}/joint_states"]
        assert js.msgtype == "sensor_msgs/msg/JointState", js
        assert abs(js.rate_hz - ran_hz) <= 5, (js, f"the robots ran {ran_hz:.1f} Hz", text[-3000:])
        assert js.count > 0.95 * ran_hz * b.duration_s  # over the whole run
        assert topics[f"/{robot}/planned"].count >= 2 and topics[f"/{robot}/joint_commands"].count == js.count
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == "/rosout"]
        logs = [reader.deserialize(raw, c.msgtype).msg for c, _, raw in reader.messages(connections=conns)]
    assert any(line.startswith("task script") and "demo.py: started" in line for line in logs), logs[:20]
    assert any(":move_rel_world done" in line for line in logs) and any("joined at" in line for line in logs)
    assert f"ROS 2 bag: {bag}" in text


def _listeners(port: int) -> set[str]:
    """The addresses a TCP port listens on, from the kernel's tables (IPv4 and IPv6)."""
    found: set[str] = set()
    for table, width in (("/proc/net/tcp", 8), ("/proc/net/tcp6", 32)):
        with open(table) as f:
            for line in list(f)[1:]:
                local, state = line.split()[1], line.split()[3]
                addr, hexport = local.split(":")
                if state == "0A" and int(hexport, 16) == port:  # 0A: LISTEN
                    if width == 8:
                        found.add(".".join(str(int(addr[i : i + 2], 16)) for i in (6, 4, 2, 0)))
                    else:
                        found.add("::" if int(addr, 16) == 0 else addr)
    return found


def test_rerun_serve_listens_on_loopback_only() -> None:
    import urllib.request

    import rerun as rr

    from cell.recorder import serve

    rec = rr.RecordingStream(application_id="cell-test-serve")
    grpc_port, web_port = free_port(), free_port()
    url = serve.serve(rec, grpc_port, web_port)
    try:
        assert url.startswith(f"http://127.0.0.1:{web_port}")
        rec.log("x", rr.Scalars(1.0))
        assert _listeners(grpc_port) == {"127.0.0.1"}  # never 0.0.0.0 or ::
        assert _listeners(web_port) == {"127.0.0.1"}
        with urllib.request.urlopen(f"http://127.0.0.1:{web_port}", timeout=10) as page:
            assert page.status == 200  # the web viewer is there, on loopback
    finally:
        serve.close(rec)
    assert _listeners(grpc_port) == set() and _listeners(web_port) == set()  # and gone with the recording


def test_rerun_serve_refuses_a_taken_port_and_says_what_to_do_instead() -> None:
    import socket

    import rerun as rr

    from cell.recorder import serve

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        rec = rr.RecordingStream(application_id="cell-test-serve")
        try:
            serve.serve(rec, port, free_port())
        except serve.ServeError as exc:
            assert "taken" in str(exc) and "save" in str(exc)
        else:
            raise AssertionError("a taken port was not refused")


SERVE_AND_WAIT = """
import sys, time
import rerun as rr
from cell.recorder import serve
rec = rr.RecordingStream(application_id="cell-test-serve")
print(serve.serve(rec, int(sys.argv[1]), int(sys.argv[2])), flush=True)
time.sleep(60)
"""


def test_the_loopback_viewer_ends_with_the_process_that_started_it_even_killed() -> None:
    """A `cell up --rerun serve` killed outright (SIGKILL: no close) leaves no viewer holding its
    ports: the kernel stops the viewer with its parent (PR_SET_PDEATHSIG)."""
    grpc_port, web_port = free_port(), free_port()
    parent = subprocess.Popen(
        [sys.executable, "-c", SERVE_AND_WAIT, str(grpc_port), str(web_port)],
        stdout=subprocess.PIPE, text=True, env=cell_env(),
    )  # fmt: skip
    try:
        assert parent.stdout is not None and parent.stdout.readline().startswith("http://127.0.0.1:")
        assert _listeners(grpc_port) == {"127.0.0.1"}  # up, in a process of its own session
    finally:
        parent.kill()
        parent.wait()
    deadline = time.monotonic() + 10
    while _listeners(grpc_port) | _listeners(web_port) and time.monotonic() < deadline:
        time.sleep(0.05)  # (polling the kernel's socket table: nothing to wait on)
    assert _listeners(grpc_port) == set() and _listeners(web_port) == set()


def test_cell_up_serve_with_its_port_taken_says_so_in_one_line_before_anything_starts(tmp_path) -> None:
    import socket

    from cell.recorder.serve import GRPC_PORT

    with socket.socket() as held:
        with contextlib.suppress(OSError):  # (taken already: the same case)
            held.bind(("127.0.0.1", GRPC_PORT))
            held.listen()
        path = write_config(tmp_path / "cell.toml", cell_overrides(run=["bus", "recorder"]))
        t0 = time.monotonic()
        done = run_cell("up", "--config", str(path), "--rerun", "serve", "--duration", "30")
    assert done.returncode == 2 and time.monotonic() - t0 < 20  # (not the 30 s of a cell that ran)
    lines = done.stderr.strip().splitlines()
    assert lines == [f"cell up: 127.0.0.1:{GRPC_PORT} is taken (another viewer?): stop it, or use "
                     "--rerun save PATH.rrd or spawn"], done.stderr  # fmt: skip


def test_the_camera_is_drawn_as_a_frustum_where_it_stands_looking_its_way(tmp_path) -> None:
    import rerun as rr

    from cell.config import load_config
    from cell.recorder.scene import camera_rotation, log_camera
    from cell.vision.acquisition import camera_spec
    from cell.vision.camera import camera_axes

    spec = camera_spec(load_config(None).vision)
    for axis in ((0.0, 0.0, 1.0), (0.6, 0.0, -0.8), (0.0, 1.0, 0.0)):
        s = replace(spec, axis=axis)
        rot = camera_rotation(s)
        assert np.allclose(rot @ [0, 0, 1], np.array(axis) / np.linalg.norm(axis))  # it looks its way
        assert np.allclose(rot @ [0, -1, 0], camera_axes(np.array(axis))[1])  # up in the image as MuJoCo's
        assert np.isclose(np.linalg.det(rot), 1.0)
    rrd = tmp_path / "camera.rrd"
    rec = rr.RecordingStream("cell-test")
    rec.save(str(rrd))
    log_camera(rec, "r1", spec)
    rec.disconnect()  # (the file is finished: its footer written)
    rows = rows_by_entity(rrd)
    assert rows["/robots/r1/camera"] >= 2  # its pose and its pinhole (the frustum)


@pytest.mark.slow
async def test_a_fleet_on_one_socket_is_drawn_from_its_group_truth(tmp_path) -> None:
    """Robots on one shared socket send their ground truth as one GroupTruth a tick (fleet/<name>): the
    recorder draws every arm's pose from it, at most FLEET_HZ, while they move.  A forged one that does
    not add up (no joints; joint values for other robots than it names) is counted and dropped."""
    from cell.recorder.live import FLEET_HZ

    rrd = tmp_path / "fleet.rrd"
    robots = [
        {"id": i, "name": f"f{i}", "skill_port": free_port(), "backend": "kinematic", "socket": "shared"}
        for i in (1, 2, 3)
    ]
    services = ["bus", "dataplane", "robots", "recorder"]
    async with saving_cell(tmp_path, robots, services, rrd) as (bus, config), Controller(bus, config) as ctl:
        for junk in (
            robot_pb2.GroupTruth(t_ns=1, joints=0, robot_id=[1], q=[0.0]),
            robot_pb2.GroupTruth(t_ns=2, joints=6, robot_id=[1, 2], q=[0.0] * 6),
        ):
            bus.publish("fleet/forged", junk)
        t0 = ctl.link.now()
        await ctl.move_together({n: Q0 + 0.3 for n in ("f1", "f2", "f3")}, speed=0.8)
        spent_s = (ctl.link.now() - t0) / 1e9
        async with asyncio.timeout(5):  # (counted with the recorder's next heartbeat)
            while True:
                rec = next(s for s in (await fetch_status(config)).services if s.name == "recorder")
                if rec.last.counters.get("bus.malformed", 0) >= 2:
                    break
                await asyncio.sleep(0.1)
        assert rec.health == "ok" and rec.last.restarts == 0
    rows = rows_by_entity(rrd)
    for name in ("f1", "f2", "f3"):
        links = [e for e in rows if e.startswith(f"/robots/{name}/links/") and not e.endswith("/geom")]
        assert len(links) == 6, links
        # drawn all along the motion, at most FLEET_HZ (and its start and end)
        assert FLEET_HZ * spent_s * 0.5 <= min(rows[e] for e in links) <= FLEET_HZ * (spent_s + 4) + 2, rows
