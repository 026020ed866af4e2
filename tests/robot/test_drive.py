"""Drive semantics: command windows, latest wins, watchdog stop and resume, velocity/acceleration limits."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cell.robot.drive import Drives

V_MAX, A_MAX = np.full(6, np.pi), np.full(6, 5.0)


def drives(robots: int = 2) -> Drives:
    return Drives(robots, V_MAX, A_MAX, watchdog=3)


def cmd(d: Drives, robot: int, joint: int, v: float) -> None:
    d.command(np.array([robot]), np.array([joint]), np.array([v]))


def test_latest_command_wins_and_executes_only_at_window_end() -> None:
    d = drives()
    for v in (0.1, 0.7, -0.3):
        cmd(d, 0, 2, v)
    assert d.target[0, 2] == 0.0  # nothing executes before the window ends
    d.end_window()
    assert d.target[0, 2] == -0.3
    assert d.target[1].tolist() == [0.0] * 6


def test_latest_wins_within_one_batch() -> None:
    d = drives()
    d.command(np.array([0, 1, 0, 0]), np.array([1, 1, 1, 4]), np.array([0.5, 0.9, -0.2, 0.3]))
    d.end_window()
    assert d.target[0, 1] == -0.2 and d.target[1, 1] == 0.9 and d.target[0, 4] == 0.3


def test_a_window_without_command_keeps_the_last_one() -> None:
    d = drives()
    cmd(d, 0, 0, 1.0)
    d.end_window()
    d.end_window()
    assert d.target[0, 0] == 1.0


def feed(d: Drives, robot: int, v: float) -> None:
    d.command(np.full(6, robot), np.arange(6), np.full(6, v))


def test_watchdog_stops_after_three_empty_windows_and_commands_resume() -> None:
    d = drives()
    feed(d, 0, 1.0)
    feed(d, 1, 1.0)
    d.end_window()
    for _ in range(2):
        feed(d, 1, 1.0)  # robot 1 keeps being fed
        stopped, _ = d.end_window()
        assert stopped.size == 0
    feed(d, 1, 1.0)
    stopped, resumed = d.end_window()  # third window without a command for robot 0
    assert stopped.tolist() == [0] and resumed.size == 0
    assert d.stopped.tolist() == [True, False]
    assert d.target[0].tolist() == [0.0] * 6 and d.target[1, 0] == 1.0
    assert d.stops == 1
    feed(d, 0, 0.5)
    _, resumed = d.end_window()
    assert resumed.tolist() == [0]
    assert not d.stopped[0] and d.target[0, 3] == 0.5


def test_one_starved_joint_stops_the_whole_robot() -> None:
    d = drives(1)
    feed(d, 0, 1.0)
    d.end_window()
    for _ in range(3):
        d.command(np.zeros(5, int), np.arange(5), np.full(5, 1.0))  # joint 5 gets nothing
        stopped, _ = d.end_window()
    assert stopped.tolist() == [0] and d.target[0].tolist() == [0.0] * 6


def test_an_uncommanded_robot_just_stands() -> None:
    d = drives(1)
    for _ in range(10):
        stopped, _ = d.end_window()
        assert stopped.size == 0
    assert not d.stopped[0] and d.stops == 0


def test_protective_stop_decelerates_within_limits() -> None:
    d = drives(1)
    d.velocity[:] = 3.0
    feed(d, 0, 3.0)
    d.end_window()
    for _ in range(3):
        d.end_window()
    assert d.stopped[0]
    speeds = []
    for _ in range(400):
        d.step(0.002)
        speeds.append(d.velocity[0, 0])
    steps = np.diff([3.0, *speeds])
    assert np.all(steps >= -5.0 * 0.002 - 1e-12)  # never faster than a_max
    assert speeds[-1] == 0.0  # 3 rad/s at 5 rad/s^2: stopped within 0.6 s


@settings(max_examples=200)
@given(
    targets=st.lists(st.floats(-100, 100), min_size=6, max_size=6),
    start=st.lists(st.floats(-3.1, 3.1), min_size=6, max_size=6),
    dt=st.floats(1e-4, 0.01),
)
def test_limits_hold_whatever_is_commanded(targets: list[float], start: list[float], dt: float) -> None:
    d = drives(1)
    d.velocity[0] = start
    feed(d, 0, 0.0)
    d.command(np.zeros(6, int), np.arange(6), np.array(targets))
    d.end_window()
    for _ in range(20):
        before = d.velocity.copy()
        mean = d.step(dt)
        assert np.all(np.abs(d.velocity) <= np.pi + 1e-12)
        assert np.all(np.abs(d.velocity - before) <= 5.0 * dt + 1e-12)
        assert np.all(np.abs(mean) <= np.pi + 1e-12)


def test_reaches_the_target_at_the_acceleration_limit() -> None:
    d = drives(1)
    feed(d, 0, 1.0)
    d.end_window()
    for _ in range(100):  # 0.2 s at 5 rad/s^2 reaches exactly 1.0
        d.step(0.002)
    assert d.velocity[0] == pytest.approx(np.full(6, 1.0))
