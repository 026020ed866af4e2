"""The modular robot's engine (cell.modular.robot), sans IO: motions, refusals, a module pulled and back."""

from __future__ import annotations

import numpy as np
import pytest

from cell.modular.robot import ModularRobot, ModuleState, MotionRefused
from cell.modular.vdc import WHERE_LOCAL, WHERE_MASTER


def run_to_end(robot: ModularRobot, limit: int = 20_000):
    for _ in range(limit):
        if (ended := robot.cycle()) is not None:
            return ended
    raise AssertionError("the motion did not end")


def test_joint_and_tool_moves_end_on_their_goals_within_the_aims() -> None:
    robot = ModularRobot(where=(WHERE_MASTER,) * 3 + (WHERE_LOCAL,) * 3)
    goal = robot.vdc.arm.q + np.array([0.4, -0.3, 0.2, 0.3, -0.2, 0.5])
    robot.move(joints=goal.tolist(), speed=1.0)
    e = run_to_end(robot)
    assert e.failed == "" and e.path == "joints" and e.guessed == 0
    assert e.tool_error_mm_max < 2.0  # the aim for the modular arm, no loss
    for _ in range(200):  # it holds there
        assert robot.cycle() is None
    assert np.abs(robot.vdc.arm.q - goal).max() < 1e-3
    target = robot.vdc.arm.tool_position() + np.array([0.05, -0.1, 0.08])
    robot.move(tool=target.tolist(), speed=0.8)
    e = run_to_end(robot)
    assert e.path == "tool" and e.tool_error_mm_max < 2.0
    for _ in range(200):
        robot.cycle()
    assert np.linalg.norm(robot.vdc.arm.tool_position() - target) < 5e-4


def test_bad_motions_are_refused_with_the_reason_and_nothing_moves() -> None:
    robot = ModularRobot()
    q0 = robot.vdc.arm.q
    cases = {
        "joints must be 6 finite numbers": dict(joints=[0.0] * 5),
        "joints must be 6 finite numbers ": dict(joints=[0.0, 0.0, float("nan"), 0.0, 0.0, 0.0]),
        "no path 'square'": dict(path="square"),
        "speed must be a positive": dict(joints=q0.tolist(), speed=-1.0),
        "a motion needs joints": {},
        "the tool position (3.0, 0.0, 0.0) m": dict(tool=[3.0, 0.0, 0.0]),
    }
    for why, kwargs in cases.items():
        with pytest.raises(MotionRefused, match=why.strip().replace("(", r"\(").replace(")", r"\)")):
            robot.move(**kwargs)
    with pytest.raises(MotionRefused, match="no module 'j9'"):
        robot.unplug("j9")
    robot.move(joints=(q0 + 0.2).tolist())
    with pytest.raises(MotionRefused, match="one motion at a time"):
        robot.move(joints=q0.tolist())
    assert robot.motion is not None and robot.motion.path == "joints"  # the first one goes on


@pytest.mark.slow
def test_an_unplugged_module_stops_the_arm_where_it_stood_until_it_is_back() -> None:
    robot = ModularRobot(lost_cycles=20)
    robot.move(path="circle")
    for _ in range(300):  # the approach (already at home: 50 ms) and into the circle
        assert robot.cycle() is None
    robot.unplug("j3")
    e = run_to_end(robot, 100)
    # the master guessed j3 from continuity until it counted it lost, then stopped the motion
    assert e.failed.startswith("module j3 unplugged") and e.path == "circle"
    assert 19 <= e.cycles - 300 <= 21
    assert robot.vdc.guessed_by[2] > 0 and robot.vdc.guessed_by[[0, 1, 3, 4, 5]].sum() == 0
    with pytest.raises(MotionRefused, match="module j3 unplugged"):
        robot.move(joints=robot.vdc.arm.q.tolist())
    held = robot.vdc.arm.tool_position()
    for _ in range(1000):  # a second on j3's brake and the others' VDC: it stays where it stood
        robot.cycle()
    assert np.linalg.norm(robot.vdc.arm.tool_position() - held) < 5e-3
    assert robot.states[2] is ModuleState.UNPLUGGED and robot.stopped
    robot.plug("j3")
    robot.cycle()
    assert robot.states[2] is ModuleState.RUNNING and robot.stopped == ""
    robot.move(path="circle")  # from where it held: home first, then the circle, within the aim
    e = run_to_end(robot)
    assert e.failed == "" and e.tool_error_mm_max < 2.0 and e.guessed == 0


def test_lost_messages_are_guessed_and_the_arm_keeps_to_its_path() -> None:
    robot = ModularRobot(loss=0.01, seed=3)
    robot.move(path="circle")
    e = run_to_end(robot)
    assert e.failed == "" and e.guessed > 100  # 1 % of 24 messages a cycle over 2.4 s
    assert e.tool_error_mm_max < 5.0  # the aim at 1 % loss
    assert all(s is ModuleState.RUNNING for s in robot.states)  # isolated losses: nobody suspect at the end


def test_with_adaptation_its_modules_move_their_inertial_parameters_as_it_moves() -> None:
    """[modular] adapt: each module's parameters adapted as the arm runs; without, they stay."""
    moved = []
    for adapt in (0.0, 100.0):
        robot = ModularRobot(adapt=adapt)
        start = [m.theta.copy() for m in robot.vdc.modules]
        robot.move(joints=(robot.vdc.arm.q + 0.3).tolist(), speed=1.0)
        e = run_to_end(robot)
        assert e.failed == "" and e.tool_error_mm_max < 2.0
        moved.append(max(np.abs(m.theta - s).max() for m, s in zip(robot.vdc.modules, start, strict=True)))
    assert moved[0] == 0.0 and moved[1] > 1e-3, moved
