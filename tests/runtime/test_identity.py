"""The cell's identity on its bus (issue 36, part 2): a service of another start of the cell (a
second `cell up`'s, or one a dead start left running) or a node of another cell is refused at the
handshake and counted; the cell's own members and clients join."""

from __future__ import annotations

import asyncio
import subprocess
import sys

import pytest

from cell.bus import Bus, BusTimeout
from cell.launcher import fetch_status
from cell.v1 import controller_pb2
from tests.conftest import cell_env, free_port, run_cell, write_config

ROBOTS = [{"id": 1, "name": "r1", "skill_port": free_port(), "backend": "kinematic"}]


async def bus_counter(cell, key: str) -> float:
    st = await fetch_status(cell.config)
    return next(s for s in st.services if s.name == "bus").last.counters.get(key, 0.0)


@pytest.mark.slow
async def test_a_service_of_another_start_never_joins_and_is_counted(start_cell) -> None:
    cell = await start_cell(run=["bus", "dataplane", "robots"], robots=ROBOTS)
    st = await fetch_status(cell.config)
    assert len(st.member) == 16  # this start's token, for the launchers of the cell's other hosts
    assert await bus_counter(cell, "forwarder.refused") == 0
    # a controller of another start of this cell: what a second `cell up` started, or a dead one left
    env = cell_env() | {"CELL_MEMBER": "0123456789abcdef"}
    cmd = [sys.executable, "-m", "cell", "service", "controller", "--config", str(cell.path)]
    alien = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        async with asyncio.timeout(20):  # refused at the handshake, and counted by the forwarder
            while await bus_counter(cell, "forwarder.refused") < 1:
                await asyncio.sleep(0.2)
        # it never joined: no controller answers on this bus (two controllers on the same tables
        # was the fault)
        async with Bus.connect(cell.config.bus, "client") as bus:
            with pytest.raises(BusTimeout):
                req = controller_pb2.RobotRequest(robot="r1")
                await bus.request("controller", "pose", req, controller_pb2.PoseReply, 1.5)
    finally:
        alien.terminate()
        _, err = alien.communicate(timeout=10)
    assert "refused this node of cell 'default' (a member of a `cell up` of its own)" in err, err[-2000:]
    # the same service with this start's token joins: it answers
    env["CELL_MEMBER"] = st.member
    member = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        async with Bus.connect(cell.config.bus, "client") as bus, asyncio.timeout(20):
            while True:
                try:
                    req = controller_pb2.RobotRequest(robot="r1")
                    await bus.request("controller", "pose", req, controller_pb2.PoseReply, 1.0)
                    break
                except BusTimeout:
                    continue
    finally:
        member.terminate()
        member.communicate(timeout=10)


async def test_a_client_of_another_cell_is_refused_in_one_line(start_cell, tmp_path) -> None:
    cell = await start_cell(run=["bus"], robots=ROBOTS)
    before = await bus_counter(cell, "forwarder.refused")
    other = tmp_path / "other.toml"
    write_config(
        other, {"cell": {"name": "other"}, "bus": {"pub": cell.config.bus.pub, "sub": cell.config.bus.sub}}
    )
    res = await asyncio.to_thread(run_cell, "status", "--config", str(other))
    assert res.returncode == 1, res
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "refused this node of cell 'other'" in lines[0], res.stderr
    assert "Traceback" not in res.stderr
    async with asyncio.timeout(10):  # counted (the bus's next heartbeat carries it)
        while await bus_counter(cell, "forwarder.refused") <= before:
            await asyncio.sleep(0.2)
    # and a second cell up of that name on the same address is refused before it starts anything
    res = await asyncio.to_thread(run_cell, "up", "--config", str(other), "--duration", "5")
    assert res.returncode == 1 and "taken by another cell's bus (not 'other''s)" in res.stderr, res.stderr
