"""The robot client library and `cell run` against live cells."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import sys

import pytest

from cell.bus import Bus
from cell.skills.client import (
    Break,
    ConnectionLost,
    MoveJoints,
    MoveRelWorld,
    MoveTo,
    MoveToolZ,
    RobotClient,
    SetSpeed,
    SkillError,
)
from cell.v1 import skills_pb2
from tests.conftest import ROOT, cell_env, cell_overrides, free_port, write_config

SERVICES = ["bus", "dataplane", "robots", "controller", "skills"]
HOME = (0.0, -90.0, 90.0, -90.0, -90.0, 0.0)


def kinematic(n: int = 1) -> list[dict]:
    return [
        {"id": i, "name": f"r{i}", "skill_port": free_port(), "backend": "kinematic"} for i in range(1, n + 1)
    ]


def test_commands_give_their_messages() -> None:
    assert MoveTo(1, 2, 3, 0, 180, 0).get_messages() == [("move_to", (1, 2, 3, 0, 180, 0)), ("break", ())]
    assert MoveToolZ(-50.0, brk=False).get_messages() == [("move_rel_tool", (0, 0, -50.0, 0, 0, 0))]
    assert SetSpeed(40).get_messages() == [("set_speed", (40,))]
    with pytest.raises(ValueError, match="6 joint values"):
        MoveJoints(joints=(1, 2, 3))
    with pytest.raises(ValueError, match="percentage"):
        SetSpeed(0)
    with pytest.raises(AttributeError):
        MoveTo(1, 2, 3).x = 5  # type: ignore[misc]  # immutable


@pytest.mark.slow
async def test_cmdexec_acks_errors_sharing_and_joined(start_cell) -> None:
    cell = await start_cell(run=SERVICES, robots=kinematic())
    r = cell.config.robots[0]
    async with Bus.connect(cell.config.bus, "script") as bus:
        traces = await bus.subscribe("run/r1/request")
        async with RobotClient("r1", "127.0.0.1", r.skill_port, bus) as robot:
            acks = await robot.cmdexec(SetSpeed(70), MoveRelWorld(x=50.0))
            assert [a.skill for a in acks] == ["set_speed", "move_rel_world", "break"]
            assert all(a.status == "done" for a in acks) and len({a.id for a in acks}) == 3
            assert acks[-1].t_end >= acks[1].t_end and acks[1].sent_ns < acks[1].received_ns
            start = acks[0].pose
            assert abs(acks[-1].pose[0] - start[0] - 50.0) < 0.5  # measured, after the break
            # an error reply raises, carrying it; the connection goes on working
            with pytest.raises(SkillError) as info:
                await robot.cmdexec(MoveTo(3000, 0, 0, 0, 180, 0))
            assert info.value.code == "unreachable" and info.value.skill == "move_to"
            # shared between coroutines: replies are matched by id
            got = await asyncio.gather(*(robot.cmdexec(Break()) for _ in range(5)))
            assert all(len(g) == 1 and g[0].status == "done" for g in got)
            # joined: all messages at once, every ack in order
            joined = await robot.cmdexec_joined(MoveRelWorld(y=30.0, brk=False), MoveRelWorld(y=-30.0))
            assert [a.skill for a in joined] == ["move_rel_world", "move_rel_world", "break"]
            assert joined[0].t_end <= joined[1].t_start + 1e-3
            # each joined message carries its own send time (the gaps between them are measured, not 0)
            assert joined[0].sent_ns < joined[1].sent_ns < joined[2].sent_ns
            t = (await traces.recv(timeout=5)).decode(skills_pb2.RequestTrace)
            assert t.robot == "r1" and t.sent_ns < t.received_ns and t.skill == "set_speed"
            # a per-call timeout
            with pytest.raises(TimeoutError):
                await robot.cmdexec(MoveRelWorld(x=200.0), timeout=0.05)


async def test_a_connection_lost_mid_command_raises_and_sends_nothing_again(start_cell) -> None:
    cell = await start_cell(run=SERVICES, robots=kinematic())
    robot = await RobotClient("r1", "127.0.0.1", cell.config.robots[0].skill_port).connect()
    try:
        pending = asyncio.create_task(robot.cmdexec(SetSpeed(10), MoveRelWorld(x=150.0)))
        await asyncio.sleep(0.5)  # under way: the slow motion's break is unanswered
        cell.proc.send_signal(signal.SIGTERM)
        with pytest.raises(ConnectionLost):
            await pending
        with pytest.raises(ConnectionLost):  # and no later command goes out on a dead connection
            await robot.cmdexec(Break())
    finally:
        await robot.close()


@pytest.mark.slow
async def test_example_scripts_run_end_to_end_one_after_another_on_one_cell(start_cell) -> None:
    """Each example as a user runs it (`cell run`), against one cell that stays up between them (as a
    user's does); the README's script below starts its own (`--up`)."""
    cell = await start_cell(run=SERVICES, robots=kinematic(2))
    for script in ("pick_and_place.py", "sync_motion.py", "wait_for_event.py"):
        path = ROOT / "examples" / script
        cmd = [sys.executable, "-m", "cell", "run", "--config", str(cell.path), str(path)]
        proc = await asyncio.create_subprocess_exec(
            *cmd,
            env=cell_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        async with asyncio.timeout(120):
            out, err = await proc.communicate()
        assert proc.returncode == 0, (script, err.decode()[-3000:])
        assert out.strip(), (script, err.decode()[-2000:])


def test_cell_run_reports_a_broken_script(tmp_path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text("def main(cell):\n    pass\n")
    proc = subprocess.run(
        [sys.executable, "-m", "cell", "run", str(bad)],
        env=cell_env(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2 and "async def main(cell)" in proc.stderr


@pytest.mark.slow
def test_the_readmes_first_script_runs(tmp_path) -> None:
    """The ten-line task script README.md shows a newcomer runs as written."""
    text = (ROOT / "README.md").read_text()
    script = text.split("## A first task script", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    assert len(script.strip().splitlines()) <= 12
    path = tmp_path / "hello.py"
    path.write_text(script)
    cfg = write_config(tmp_path / "cell.toml", cell_overrides(kinematic(2), run=SERVICES))
    proc = subprocess.run(
        [sys.executable, "-m", "cell", "run", "--up", "--config", str(cfg), str(path)],
        env=cell_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    pose = proc.stdout.split("r1's tool at", 1)[1].strip().splitlines()[0]
    assert len(pose.strip("()").split(",")) == 6, proc.stdout
