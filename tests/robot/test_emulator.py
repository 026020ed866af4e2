"""Robot groups over real UDP sockets on loopback, ticked by hand (deterministic)."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from cell.config import load_config
from cell.robot import datagram, udp
from cell.robot.arm import arm_model
from cell.robot.backends import MujocoArms, joint_torques
from cell.robot.datagram import Datagram, Kind
from cell.robot.emulator import RobotGroup
from tests.conftest import cell_overrides

Q0 = [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]


@pytest.fixture(params=[(s, t) for t in ("native", "python") for s in ("own", "shared")], ids="-".join)
def plant(request):
    """A socket standing in for the data plane, and a factory of robot groups sending to it: robots
    with a socket each (a real arm's) and with one for the group (a fleet's), the same semantics;
    ticked in C (cell/robot/tick.c) and by the Python model, the same semantics again."""
    sockets, tick = request.param
    dp = udp.open_socket("127.0.0.1")
    groups: list[RobotGroup] = []

    def make(backend: str = "kinematic", n: int = 1) -> RobotGroup:
        robots = [
            {
                "id": 10 + i,
                "name": f"t{i}",
                "skill_port": 3000 + i,
                "backend": backend,
                "socket": sockets,
                "tick": tick,
            }
            for i in range(n)
        ]
        cfg = load_config(overrides={**cell_overrides(), "robots": robots})
        host, port = dp.getsockname()
        g = RobotGroup(cfg.robots, f"{host}:{port}")
        groups.append(g)
        assert g.tick_impl == tick, g.tick_why  # (a C tick that does not build is a failure)
        return g

    yield dp, make
    for g in groups:
        g.close()
    dp.close()


def status_from(dp: socket.socket) -> list[Datagram]:
    out = []
    while (got := udp.recv_batch(dp)) is not None:
        data, seg, _, _ = got
        out += [datagram.decode(data[i : i + seg]) for i in range(0, len(data), seg)]
    return out


def ticks(g: RobotGroup, n: int) -> list:
    return [g.tick(deadline=float("inf")) for _ in range(n)]  # never late: timing is not under test


def command_all(dp: socket.socket, g: RobotGroup, row: int, v: list[float]) -> None:
    addr = g.socks[0 if g.shared else row].getsockname()
    for j, vj in enumerate(v):
        dp.sendto(datagram.encode(Datagram(int(g.ids[row]), j, Kind.COMMAND, 0, vj, 0.0)), addr)


def test_status_stream(plant) -> None:
    dp, make = plant
    g = make(n=2)
    ticks(g, 3)
    got = status_from(dp)
    assert len(got) == 3 * 2 * 6
    assert {(d.robot_id, d.joint_id) for d in got} == {(r, j) for r in (10, 11) for j in range(6)}
    assert all(d.kind is Kind.STATUS for d in got)
    assert sorted(d.seq for d in got if (d.robot_id, d.joint_id) == (11, 4)) == [1, 2, 3]
    assert [d.position for d in got[:6]] == pytest.approx(Q0, abs=1e-7)
    assert g.counters.status_sent == 36 and g.counters.late_sends == 0


def test_each_robot_takes_only_its_own_commands_whatever_socket_they_came_to(plant) -> None:
    dp, make = plant
    g = make(n=3)
    assert len(g.socks) == (1 if g.shared else 3) and len(set(g.addresses())) == len(g.socks)
    ticks(g, 1)
    command_all(dp, g, 1, [0.2] * 6)
    command_all(dp, g, 2, [-0.1] * 6)
    ticks(g, 4)  # the window ends
    assert g.drives.target[:, 0].tolist() == pytest.approx([0.0, 0.2, -0.1], abs=1e-7)
    assert g.counters.commands == 12 and sum(g.counters.rejected.values()) == 0


def test_commands_execute_at_the_window_end_latest_first(plant) -> None:
    dp, make = plant
    g = make()
    assert g.window_ticks == 4  # 500 Hz status, 125 Hz commands
    ticks(g, 1)  # tick 0
    for v in (0.1, 0.2, 0.3):
        command_all(dp, g, 0, [v] * 6)
    ticks(g, 3)  # ticks 1-3: still the first window
    assert g.drives.target[0].tolist() == [0.0] * 6
    ticks(g, 1)  # tick 4 ends the window
    assert g.drives.target[0].tolist() == pytest.approx([0.3] * 6, abs=1e-7)
    assert g.counters.commands == 18
    for _ in range(15):  # keep commanding every window (or the watchdog stops the robot)
        command_all(dp, g, 0, [0.3] * 6)
        ticks(g, 4)
    last = status_from(dp)[-6:]
    assert [d.velocity for d in last] == pytest.approx([0.3] * 6, abs=1e-6)


def test_an_answer_to_the_status_that_ends_a_window_counts_in_the_next_window(plant) -> None:
    """A data plane in the kernel answers within microseconds, before the tick that sent the status
    takes its commands: such an answer must miss the window ending then, as on a real arm."""
    dp, make = plant
    g = make()
    ticks(g, 4)  # ticks 0-3; tick 4 ends the first window
    command_all(dp, g, 0, [0.1] * 6)  # in time for it

    def answer() -> None:  # called as the status has gone out: answer it at once
        if not answered:
            answered.append(True)
            command_all(dp, g, 0, [0.5] * 6)

    answered: list[bool] = []
    g.at_deadline = answer
    g.tick(deadline=float("inf"))  # tick 4
    g.at_deadline = None
    assert answered and g.counters.commands == 12  # both batches were taken in this tick
    assert g.drives.target[0].tolist() == pytest.approx([0.1] * 6, abs=1e-7)
    ticks(g, 3)  # ticks 5-7: the answer waits for its window
    assert g.drives.target[0].tolist() == pytest.approx([0.1] * 6, abs=1e-7)
    ticks(g, 1)  # tick 8
    assert g.drives.target[0].tolist() == pytest.approx([0.5] * 6, abs=1e-7)


def test_malformed_and_foreign_datagrams_are_counted_and_dropped(plant) -> None:
    dp, make = plant
    g = make()
    addr = g.socks[0].getsockname()
    good = Datagram(10, 1, Kind.COMMAND, 0, 0.25, 0.0)
    junk = [
        b"",
        b"short",
        datagram.encode(good) + b"x",  # 25 bytes
        datagram.encode(Datagram(10, 1, Kind.STATUS, 0, 9.0, 0.0)),  # a status sent to a robot
        datagram.encode(Datagram(99, 1, Kind.COMMAND, 0, 9.0, 0.0)),  # another robot's command
        datagram.encode(Datagram(10, 7, Kind.COMMAND, 0, 9.0, 0.0)),  # no joint 7
        bytes([0, 10, 1, 3]) + bytes(20),  # kind 3
    ]
    for j in junk:
        dp.sendto(j, addr)
    dp.sendto(datagram.encode(good), addr)
    ticks(g, 5)
    assert g.counters.rejected == {"length": 3, "kind": 2, "robot": 1, "joint": 1}
    assert g.counters.commands == 1
    assert g.drives.target[0, 1] == pytest.approx(0.25, abs=1e-7)  # the good one still worked


def test_watchdog_stops_then_commands_resume(plant) -> None:
    dp, make = plant
    g = make()
    ticks(g, 1)
    command_all(dp, g, 0, [0.5] * 6)
    ev = ticks(g, 4)  # window 1 ends at tick 4: commanded
    assert all(s.size == 0 for s, _ in ev)
    ev = ticks(g, 12)  # three windows with nothing
    stops = [s.tolist() for s, _ in ev if s.size]
    assert stops == [[0]] and g.drives.stopped[0]
    ticks(g, 150)
    assert np.abs(g.backend.qd[0]).max() == 0.0  # decelerated to rest
    command_all(dp, g, 0, [0.1] * 6)
    ev = ticks(g, 4)
    assert [r.tolist() for _, r in ev if r.size] == [[0]]
    assert not g.drives.stopped[0]


def test_a_catch_up_after_the_process_was_held_up_stops_on_the_watchdog_not_on_the_last_command(
    plant,
) -> None:
    """A robot process the OS held up for 2 s catches up in one tick; the robot it stands for would
    have seen each of those windows pass without a command and stopped: so must the emulated one."""
    dp, make = plant
    g = make()
    ticks(g, 1)
    command_all(dp, g, 0, [0.5] * 6)
    ticks(g, 4)  # the window ends: the robot runs at up to 0.5 rad/s
    q_before = g.backend.q[0].copy()
    stopping, _ = g.tick(deadline=float("inf"), periods=round(2.0 / g.period))
    assert stopping.tolist() == [0] and g.drives.stopped[0]
    moved = float(np.abs(g.backend.q[0] - q_before).max())
    # at most the watchdog's windows (+1 under way) at 0.5 rad/s, then the braking from it
    window_s = g.window_ticks * g.period
    bound = 0.5 * (g.drives.watchdog + 1) * window_s + 0.5**2 / (2 * float(g.drives.a_max.min()))
    assert moved <= bound < 0.2, (moved, bound)  # (2 s at 0.5 rad/s would be 1 rad)


def test_a_silenced_robot_sends_nothing_hears_nothing_and_its_watchdog_stops_it(plant) -> None:
    dp, make = plant
    g = make(n=2)
    ticks(g, 1)
    command_all(dp, g, 0, [0.5] * 6)
    command_all(dp, g, 1, [0.5] * 6)
    ticks(g, 4)  # a fed window: both drives armed and moving
    status_from(dp)
    assert g.silence(11, 5.0) and not g.silence(99, 5.0)
    for _ in range(16):  # both are commanded on; robot 11 hears none of it
        command_all(dp, g, 0, [0.5] * 6)
        command_all(dp, g, 1, [0.25] * 6)
        ticks(g, 1)
    got = status_from(dp)
    assert got and {d.robot_id for d in got} == {10}  # and says nothing
    assert not g.drives.stopped[0] and g.drives.stopped[1]  # its watchdog stopped it
    g.silent_until[:] = 0.0  # the cable is back: fed again, it resumes
    for _ in range(8):
        command_all(dp, g, 1, [0.25] * 6)
        command_all(dp, g, 0, [0.5] * 6)
        ticks(g, 1)
    assert not g.drives.stopped[1] and g.drives.target[1, 0] == pytest.approx(0.25, abs=1e-7)


def test_mujoco_group_follows_commands(plant) -> None:
    dp, make = plant
    g = make("mujoco")
    for _ in range(100):  # 0.2 s of commands every window
        command_all(dp, g, 0, [0.5, 0, 0, 0, 0, -0.5])
        ticks(g, 4)
    status = status_from(dp)[-6:]
    assert status[0].velocity == pytest.approx(0.5, rel=0.01)
    assert status[5].velocity == pytest.approx(-0.5, rel=0.01)
    assert abs(status[2].velocity) < 0.005


def test_each_robot_announces_itself_where_it_lives(plant) -> None:
    """A robot's own announcement (what it answers to `announce`) is its row of the group's: its
    id and name, and the socket it sends from (the group's one, in a fleet)."""
    from cell.robot.node import announcement, announcements

    _, make = plant
    g = make(n=3)
    every = announcements(g, "127.0.0.1:50000")
    for row in range(3):
        one = announcement(g, row, "127.0.0.1:50000")
        assert one.robot_id == 10 + row and one.name == f"t{row}"
        host, port = g.socks[0 if g.shared else row].getsockname()[:2]
        assert one.udp_address == f"{host}:{port}"
        assert one.SerializeToString() == every[row].SerializeToString()


def test_a_mujoco_arm_reports_its_drives_torques_and_none_beyond_them_in_free_space() -> None:
    """Standing still, its drives hold it against gravity (what RTDE's target_moment reports); nothing
    touches it, so get_joint_torques()'s share is nil."""
    arm = arm_model("ur5e")
    q0 = np.array([[0.0, -1.2, 1.0, -1.4, -1.57, 0.0]])
    b = MujocoArms(arm, q0, 4)
    for _ in range(200):
        b.step(0.002)
    motor, beyond = joint_torques(b.data[0], arm.dof)
    d = b.data[0]
    gravity = d.qfrc_bias[: arm.dof]  # (still: the bias is gravity alone)
    assert abs(motor[1]) > 10.0 and np.abs(motor - gravity).max() < 0.02 * np.abs(gravity).max()
    assert np.abs(beyond).max() < 1e-9
