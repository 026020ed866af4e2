"""`cell follow` on a running cell: trajectories from ROS 2 bags (MCAP and SQLite, written with
rosbags as ROS tools write them), JSON and CSV; what cannot be run is refused in one line, exit 2,
nothing moved."""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from cell.bus import Bus, RemoteError
from cell.bus.node import BusRefused, BusTimeout, BusUnavailable
from cell.launcher import fetch_status
from cell.robot.arm import arm_model
from cell.skills.client import RobotClient, SkillError
from cell.trajectory import sources
from cell.trajectory.model import Trajectory, TrajectoryError
from cell.trajectory.sources import load
from cell.trajectory.wire import to_message
from cell.v1 import controller_pb2
from tests.conftest import free_port, run_cell
from tests.trajectory.test_trajectory import Q0, UR, wave

TS = get_typestore(Stores.ROS2_HUMBLE)
# The types of control_msgs and moveit_msgs, as their .msg/.action files define them (RobotState without
# its attached collision objects, which a trajectory does not read): bags embed the definitions they
# were written with, and rosbags decodes by those, as it does a bag MoveIt or ros2_control recorded.
TYPES = {
    "control_msgs/msg/JointTolerance": (
        "string name\nfloat64 position\nfloat64 velocity\nfloat64 acceleration\n"
    ),
    "control_msgs/action/FollowJointTrajectory_Goal": (
        "trajectory_msgs/JointTrajectory trajectory\n"
        "trajectory_msgs/MultiDOFJointTrajectory multi_dof_trajectory\n"
        "control_msgs/JointTolerance[] path_tolerance\ncontrol_msgs/JointTolerance[] goal_tolerance\n"
        "builtin_interfaces/Duration goal_time_tolerance\n"
    ),
    "moveit_msgs/msg/RobotTrajectory": (
        "trajectory_msgs/JointTrajectory joint_trajectory\n"
        "trajectory_msgs/MultiDOFJointTrajectory multi_dof_joint_trajectory\n"
    ),
    "moveit_msgs/msg/RobotState": (
        "sensor_msgs/JointState joint_state\n"
        "sensor_msgs/MultiDOFJointState multi_dof_joint_state\nbool is_diff\n"
    ),
    "moveit_msgs/msg/DisplayTrajectory": (
        "string model_id\nmoveit_msgs/RobotTrajectory[] trajectory\nmoveit_msgs/RobotState trajectory_start\n"
    ),
}
for _name, _text in TYPES.items():
    TS.register(get_types_from_msg(_text, _name))


def joint_trajectory(t: np.ndarray, q: np.ndarray, names: list[str]) -> object:
    T = TS.types
    points = [
        T["trajectory_msgs/msg/JointTrajectoryPoint"](
            positions=np.ascontiguousarray(qi, np.float64),
            velocities=np.array([], np.float64),
            accelerations=np.array([], np.float64),
            effort=np.array([], np.float64),
            time_from_start=T["builtin_interfaces/msg/Duration"](sec=int(ti), nanosec=round(ti % 1 * 1e9)),
        )
        for ti, qi in zip(t, q, strict=True)
    ]
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="base"
    )
    return T["trajectory_msgs/msg/JointTrajectory"](header=header, joint_names=names, points=points)


def write_bag(path: Path, t: np.ndarray, q: np.ndarray, names: list[str], storage: StoragePlugin) -> Path:
    """A bag of one trajectory_msgs/msg/JointTrajectory on /planned, as a planner's exporter records it."""
    return write_message(path, "/planned", joint_trajectory(t, q, names), storage)


def write_message(path: Path, topic: str, msg: object, storage: StoragePlugin = StoragePlugin.MCAP) -> Path:
    with Writer(path, version=8, storage_plugin=storage) as w:
        conn = w.add_connection(topic, msg.__msgtype__, typestore=TS)
        w.write(conn, 1, TS.serialize_cdr(msg, msg.__msgtype__))
    return path


def empty_multi_dof() -> object:
    T = TS.types
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="")
    return T["trajectory_msgs/msg/MultiDOFJointTrajectory"](header=header, joint_names=[], points=[])


def display_trajectory(segments: list[tuple[np.ndarray, np.ndarray]]) -> object:
    """What MoveIt publishes on /display_planned_path: the plan's segments, each timed from 0."""
    T = TS.types
    robot_trajectories = [
        T["moveit_msgs/msg/RobotTrajectory"](
            joint_trajectory=joint_trajectory(t, q, UR), multi_dof_joint_trajectory=empty_multi_dof()
        )
        for t, q in segments
    ]
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="")
    e = np.zeros(0)
    q0 = segments[0][1][0]
    joints = T["sensor_msgs/msg/JointState"](header=header, name=UR, position=q0, velocity=e, effort=e)
    multi = T["sensor_msgs/msg/MultiDOFJointState"](
        header=header, joint_names=[], transforms=[], twist=[], wrench=[]
    )
    start = T["moveit_msgs/msg/RobotState"](joint_state=joints, multi_dof_joint_state=multi, is_diff=False)
    return T["moveit_msgs/msg/DisplayTrajectory"](
        model_id="ur5e", trajectory=robot_trajectories, trajectory_start=start
    )


def follow_goal(t: np.ndarray, q: np.ndarray) -> object:
    """A FollowJointTrajectory goal as a joint trajectory controller gets it.  (Its SendGoal request
    wraps it in one more message: rosbags cannot write an action type nested in another, but the
    cell's reader finds the trajectory at any depth.)"""
    T = TS.types
    goal = T["control_msgs/action/FollowJointTrajectory_Goal"](
        trajectory=joint_trajectory(t, q, UR), multi_dof_trajectory=empty_multi_dof(), path_tolerance=[],
        goal_tolerance=[], goal_time_tolerance=T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
    )  # fmt: skip
    return goal


def test_sources_read_bags_json_and_csv_alike(tmp_path) -> None:
    traj = wave(20, 2.0)
    order = [5, 0, 1, 2, 3, 4]  # (columns in another order than the robot's, named)
    names = [UR[i] for i in order]
    for storage in (StoragePlugin.MCAP, StoragePlugin.SQLITE3):
        (pts,) = load(write_bag(tmp_path / f"bag-{storage.name}", traj.t, traj.q[:, order], names, storage))
        assert (
            pts.joint_names == names
            and np.allclose(pts.t, traj.t)
            and np.array_equal(pts.q, traj.q[:, order])
        )
    js = tmp_path / "t.json"
    js.write_text(json.dumps({"robot": "r2", "joint_names": UR, "points": [
        {"t": float(t), "positions": q.tolist()} for t, q in zip(traj.t, traj.q, strict=True)]}))  # fmt: skip
    (pts,) = load(js)
    assert pts.robot == "r2" and np.array_equal(pts.q, traj.q) and pts.qd is None
    csv = tmp_path / "t.csv"
    rows = ["t," + ",".join(UR) + "," + ",".join(f"{n}.vel" for n in UR)]
    rows += [
        ",".join(repr(float(x)) for x in [t, *q, *np.ones(6)]) for t, q in zip(traj.t, traj.q, strict=True)
    ]
    csv.write_text("\n".join(rows) + "\n")
    (pts,) = load(csv)
    assert pts.joint_names == UR and np.array_equal(pts.q, traj.q) and (pts.qd == 1.0).all()


def test_follow_joint_trajectory_goals_and_moveits_display_trajectory_read_as_their_trajectories(
    tmp_path,
) -> None:
    traj = wave(30, 3.0)
    for storage in (StoragePlugin.MCAP, StoragePlugin.SQLITE3):
        msg = follow_goal(traj.t, traj.q)
        (pts,) = load(write_message(tmp_path / f"goal-{storage.name}", "/arm/goal", msg, storage))
        assert pts.joint_names == UR and np.allclose(pts.t, traj.t) and np.array_equal(pts.q, traj.q)
    # MoveIt's plan of two segments, each timed from 0, the second starting where the first ends: one
    # trajectory, the repeated point once
    a, b = traj.q[:16], traj.q[15:]
    msg = display_trajectory([(traj.t[:16], a), (traj.t[15:] - traj.t[15], b)])
    (pts,) = load(write_message(tmp_path / "display", "/display_planned_path", msg))
    assert pts.t.size == 30 and np.allclose(pts.t, traj.t) and np.array_equal(pts.q, traj.q)


def test_bad_bags_are_refused_in_one_line_naming_the_problem(tmp_path, monkeypatch) -> None:
    traj = wave(20, 2.0)

    def refused(path: Path, words: str, **kw) -> None:
        with pytest.raises(TrajectoryError) as e:
            load(path, **kw)
        assert words in str(e.value) and "\n" not in str(e.value), str(e.value)

    bag = write_bag(tmp_path / "cut", traj.t, traj.q, UR, StoragePlugin.MCAP)
    mcap = next(bag.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])  # truncated
    refused(bag, "not a readable ROS 2 bag")
    bag = write_bag(tmp_path / "storage", traj.t, traj.q, UR, StoragePlugin.MCAP)
    meta = bag / "metadata.yaml"
    meta.write_text(meta.read_text().replace("storage_identifier: mcap", "storage_identifier: rosbag_v1"))
    refused(bag, "not a readable ROS 2 bag")
    refused(
        write_bag(tmp_path / "ok", traj.t, traj.q, UR, StoragePlugin.MCAP),
        "no topic '/other'",
        topic="/other",
    )
    garbage = tmp_path / "garbage"
    with Writer(garbage, version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        conn = w.add_connection("/planned", "trajectory_msgs/msg/JointTrajectory", typestore=TS)
        w.write(conn, 1, b"\x00\x01\x00\x00not a trajectory")
    refused(garbage, "cannot decode trajectory_msgs/msg/JointTrajectory")
    monkeypatch.setattr(sources, "MAX_POINTS", 19)  # (the check of 10^6 points, on 20)
    refused(write_bag(tmp_path / "long", traj.t, traj.q, UR, StoragePlugin.MCAP), "20 points: at most 19")
    monkeypatch.undo()
    joints = arm_model("ur5e").joints
    for change, words in (
        (lambda t, q, n: (t[::-1], q, n), "point 1: time"),  # out of order
        (lambda t, q, n: (t, np.where(np.arange(q.size).reshape(q.shape) == 13, np.nan, q), n), "point 2"),
        (lambda t, q, n: (t, q, [*n[:5], "elbow_2_joint"]), "'elbow_2_joint' is not one of this robot's"),
    ):  # fmt: skip
        t, q, n = change(traj.t, traj.q, UR)
        (pts,) = load(
            write_bag(tmp_path / words[:8].replace(" ", "_").replace("'", ""), t, q, n, StoragePlugin.MCAP)
        )
        with pytest.raises(TrajectoryError, match=re.escape(words)):
            Trajectory.build(pts.t, pts.q, joint_names=pts.joint_names, robot_joints=joints)


@pytest.mark.slow
async def test_cell_follow_runs_a_bag_on_the_cell_and_refuses_a_bad_one_moving_nothing(
    start_cell, tmp_path
) -> None:
    robots = [{"id": 1, "name": "r1", "skill_port": free_port(), "backend": "mujoco", "truth_hz": 500}]
    cell = await start_cell(run=["bus", "dataplane", "robots", "controller"], robots=robots)
    cfg = str(cell.path)
    traj = wave(40, 4.0)
    bag = write_bag(tmp_path / "plan", traj.t, traj.q[:, ::-1], list(reversed(UR)), StoragePlugin.MCAP)
    done = await asyncio.to_thread(run_cell, "follow", str(bag), "--config", cfg, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    got = re.search(
        r"r1: 40 points over 4\.00 s .* max ([\d.]+) mm \(t = [\d.]+ s\), median ([\d.]+) mm", done.stdout
    )
    assert got is not None, done.stdout
    assert float(got.group(1)) <= 1.0 and float(got.group(2)) <= 0.1, done.stdout
    # MoveIt's DisplayTrajectory of two segments, joined, within the same bounds
    w = wave(30, 3.0)
    shown = display_trajectory([(w.t[:16], w.q[:16]), (w.t[15:] - w.t[15], w.q[15:])])
    display = write_message(tmp_path / "display", "/display_planned_path", shown)
    done = await asyncio.to_thread(run_cell, "follow", str(display), "--config", cfg, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    got = re.search(
        r"r1: 30 points over 3\.00 s .* max ([\d.]+) mm \(t = [\d.]+ s\), median ([\d.]+) mm", done.stdout
    )
    assert got is not None and float(got.group(1)) <= 1.0 and float(got.group(2)) <= 0.1, done.stdout
    # a Cartesian square of 100 mm from a JSON file of tool poses and a top speed: through IK, within
    # the same bounds
    p0 = arm_model("ur5e").fk(Q0)[0]
    corners = [p0 + d for d in ([0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0], [0, 0, 0])]
    square = tmp_path / "square.json"
    square.write_text(
        json.dumps({"name": "square", "max_speed": 0.1, "poses": [{"position": list(c)} for c in corners]})
    )
    done = await asyncio.to_thread(run_cell, "follow", str(square), "--config", cfg, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    got = re.search(
        r"r1: (\d+) points over ([\d.]+) s \(square\).* max ([\d.]+) mm \(t = [\d.]+ s\), median ([\d.]+) mm",
        done.stdout,
    )
    assert got is not None and int(got.group(1)) > 100, done.stdout
    assert float(got.group(3)) <= 1.0 and float(got.group(4)) <= 0.1, done.stdout
    far = tmp_path / "far.json"
    far.write_text(
        json.dumps({"max_speed": 0.1, "poses": [{"position": list(p0)}, {"position": [1.5, 0.0, 0.5]}]})
    )
    refused = await asyncio.to_thread(run_cell, "follow", str(far), "--config", cfg, timeout=60)
    assert (
        refused.returncode == 2
        and "waypoint 1 (1500.0, 0.0, 500.0 mm): no joint positions reach" in refused.stderr
    )
    # a point that is not a number: refused in one line, exit 2, nothing loaded or moved
    q = traj.q.copy()
    q[7, 2] = np.nan
    bad = write_bag(tmp_path / "bad", traj.t, q, UR, StoragePlugin.SQLITE3)
    async with Bus.connect(cell.config.bus, "test") as bus:
        before = await bus.request(
            "controller", "pose", controller_pb2.RobotRequest(robot="r1"), controller_pb2.PoseReply
        )
        refused = await asyncio.to_thread(run_cell, "follow", str(bad), "--config", cfg, timeout=60)
        assert refused.returncode == 2 and refused.stderr.strip().count("\n") == 0, refused.stderr
        assert "point 7: positions not a finite number" in refused.stderr
        fast = write_bag(tmp_path / "fast", traj.t / 8, traj.q, UR, StoragePlugin.MCAP)  # 8 times too fast
        refused = await asyncio.to_thread(run_cell, "follow", str(fast), "--config", cfg, timeout=60)
        assert refused.returncode == 2 and re.search(r"point \d+ \(t = [\d.]+ s\): joint \d", refused.stderr)
        missing = await asyncio.to_thread(run_cell, "follow", str(bag), "--topic", "/nope", "--config", cfg)
        assert missing.returncode == 2 and "no topic '/nope' of a trajectory type" in missing.stderr
        after = await bus.request(
            "controller", "pose", controller_pb2.RobotRequest(robot="r1"), controller_pb2.PoseReply
        )
        # (it still settles onto the first trajectory's end, by tenths of a mrad; the refused ones would
        # have swung it by tenths of a rad)
        assert np.abs(np.array(after.joints) - np.array(before.joints)).max() < 1e-3
    assert np.abs(np.array(after.joints) - Q0).max() < 2e-3  # where the trajectory ended: its start


@pytest.mark.slow
async def test_two_robots_follow_together_from_json_and_from_a_task_script(start_cell, tmp_path) -> None:
    robots = [
        {"id": i, "name": f"r{i}", "skill_port": free_port(), "backend": "mujoco", "truth_hz": 500}
        for i in (1, 2)
    ]
    cell = await start_cell(run=["bus", "dataplane", "robots", "controller", "skills"], robots=robots)
    cfg = str(cell.path)
    a, b = wave(30, 3.0), wave(30, 3.0, amp=np.array([-0.5, 0.3, -0.2, 0.4, -0.3, 0.6]))
    js = tmp_path / "two.json"
    js.write_text(json.dumps({"trajectories": [
        {"robot": name, "name": name, "joint_names": UR,
         "points": [{"t": float(t), "positions": q.tolist()} for t, q in zip(tr.t, tr.q, strict=True)]}
        for name, tr in (("r1", a), ("r2", b))]}))  # fmt: skip
    # a task script moves r2 off its start first: it is brought back while r1 waits, then both go
    script = tmp_path / "away.py"
    script.write_text(
        "import numpy as np\n"
        "from cell.trajectory.model import Trajectory\n"
        "async def main(cell):\n"
        "    q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])\n"
        "    t = np.array([0.0, 1.0, 2.0])\n"
        "    q = np.vstack([q0, q0 + 0.3, q0 + 0.3])\n"
        "    reply = await cell.follow({'r2': Trajectory.build(t, q, name='away')})\n"
        "    assert reply.t0_ns > 0\n"
    )
    ran = await asyncio.to_thread(run_cell, "run", str(script), "--config", cfg, timeout=60)
    assert ran.returncode == 0, ran.stderr[-2000:]
    done = await asyncio.to_thread(run_cell, "follow", str(js), "--config", cfg, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    for name in ("r1", "r2"):
        got = re.search(
            rf"{name}: 30 points over 3\.00 s .* max ([\d.]+) mm \(t = [\d.]+ s\), median ([\d.]+) mm",
            done.stdout,
        )
        assert got is not None and float(got.group(1)) <= 1.0 and float(got.group(2)) <= 0.1, done.stdout
    shift = re.search(r"start shift between robots: ([\d.]+) ms", done.stdout)
    assert shift is not None and float(shift.group(1)) < 2.0, done.stdout  # (one start time for both)


def ramp(q_from: np.ndarray, q_to: np.ndarray, points: int = 25, seconds: float = 2.0) -> Trajectory:
    """From rest to rest on 1 - cos: positions only."""
    t = np.linspace(0.0, seconds, points)
    s = (1 - np.cos(np.pi * t / seconds)) / 2
    return Trajectory.build(t, q_from + np.outer(s, q_to - q_from), name="ramp")


@pytest.mark.slow
async def test_skill_servers_run_named_trajectories_and_robot_clients_follow_in_turn(
    start_cell, tmp_path
) -> None:
    """follow:<name> on the AdeptServer-style skill servers, as any client sends it (raw TCP here):
    named by `cell follow --name`, each robot its own part; a name not known is an error reply and
    the connection goes on; RobotClient.follow() from a script runs one in turn with its commands."""
    robots = [
        {"id": i, "name": f"r{i}", "skill_port": free_port(), "backend": "mujoco", "truth_hz": 100}
        for i in (1, 2)
    ]
    cell = await start_cell(run=["bus", "dataplane", "robots", "controller", "skills"], robots=robots)
    cfg = str(cell.path)
    goal = {
        "r1": Q0 + np.array([0.4, -0.2, 0.2, 0.3, 0.2, 0.5]),
        "r2": Q0 - np.array([0.3, 0.1, 0.2, 0.2, 0.3, 0.4]),
    }
    js = tmp_path / "pick.json"
    entries = []
    for name, g in goal.items():
        tr = ramp(Q0, g)
        points = [{"t": float(t), "positions": q.tolist()} for t, q in zip(tr.t, tr.q, strict=True)]
        entries.append({"robot": name, "joint_names": UR, "points": points})
    js.write_text(json.dumps({"trajectories": entries}))
    named = await asyncio.to_thread(
        run_cell, "follow", str(js), "--name", "pick", "--config", cfg, timeout=60
    )
    assert named.returncode == 0 and "named 'pick': r1, r2, 50 points over 2.00 s" in named.stdout, (
        named.stderr
    )
    arm = arm_model("ur5e")
    for name in ("r1", "r2"):
        port = cell.config.robot(name).skill_port
        reader, writer = await asyncio.open_connection(cell.config.skills.host, port)
        writer.write(b"abcd0001:follow:nope\r\nabcd0002:follow:pick\r\nabcd0003:break\r\n")
        await writer.drain()
        lines = [(await asyncio.wait_for(reader.readuntil(b"\r\n"), 30)).decode() for _ in range(3)]
        writer.close()
        assert lines[0].startswith("abcd0001:error:unreachable:no trajectory named 'nope' (named: pick)"), (
            lines
        )
        assert lines[1].startswith("abcd0002:done:") and lines[2].startswith("abcd0003:done:"), lines
        x, y, z = (float(v) for v in lines[2].split(":")[3].split(",")[:3])  # the pose it stands at, mm
        want = arm.fk(goal[name])[0] * 1000
        assert np.abs(np.array([x, y, z]) - want).max() < 0.5, (lines[2], want)
    async with Bus.connect(cell.config.bus, "test") as bus:
        # names that cannot travel in a skill command, and no trajectories: refused, nothing kept
        one = to_message("r1", ramp(Q0, goal["r1"]).t, ramp(Q0, goal["r1"]).q)
        for req, words in (
            (
                controller_pb2.NameRequest(name="p ick", trajectories=[one]),
                "bad_request: a trajectory's name is",
            ),
            (
                controller_pb2.NameRequest(name="x" * 65, trajectories=[one]),
                "bad_request: a trajectory's name is",
            ),
            (controller_pb2.NameRequest(name="empty"), "bad_request: no trajectories"),
        ):
            with pytest.raises(RemoteError, match=re.escape(words)):
                await bus.request("controller", "name", req, controller_pb2.NameReply)
        robot = await RobotClient(
            "r1", cell.config.skills.host, cell.config.robot("r1").skill_port, bus
        ).connect()
        try:
            acks = await robot.follow(ramp(goal["r1"], Q0), speed=50)
            assert [a.skill for a in acks] == ["set_speed", "follow", "break"]
            with pytest.raises(SkillError, match=r"follow .* plan: robot 1: trajectory 'ramp': point \d+"):
                await robot.follow(ramp(Q0, Q0 + 1.0, seconds=0.2))  # far too fast: refused, nothing moved
        finally:
            await robot.close()
        pose = await bus.request(
            "controller", "pose", controller_pb2.RobotRequest(robot="r1"), controller_pb2.PoseReply
        )
    assert np.abs(np.array(pose.joints) - Q0).max() < 1e-3


@pytest.mark.slow
async def test_a_named_trajectory_is_followed_after_the_controller_is_killed_and_restarted(
    start_cell, tmp_path
) -> None:
    """Named trajectories are kept in the cell's state directory: the controller's process SIGKILLed,
    its supervisor's next one has them, and follow:<name> runs as before."""
    robots = [{"id": 1, "name": "r1", "skill_port": free_port(), "backend": "kinematic", "truth_hz": 100}]
    cell = await start_cell(run=["bus", "dataplane", "robots", "controller", "skills"], robots=robots)
    goal = Q0 + np.array([0.3, -0.2, 0.2, 0.1, 0.2, 0.4])
    tr = ramp(Q0, goal)
    js = tmp_path / "pick.json"
    points = [{"t": float(t), "positions": q.tolist()} for t, q in zip(tr.t, tr.q, strict=True)]
    js.write_text(json.dumps({"trajectories": [{"robot": "r1", "joint_names": UR, "points": points}]}))
    named = await asyncio.to_thread(
        run_cell, "follow", str(js), "--name", "pick", "--config", str(cell.path), timeout=60
    )
    assert named.returncode == 0, named.stderr
    before = next(s for s in (await fetch_status(cell.config)).services if s.name == "controller").last.pid
    os.kill(before, signal.SIGKILL)
    async with asyncio.timeout(60):  # (its supervisor starts another)
        while True:
            try:
                status = await fetch_status(cell.config)
            except BusRefused:
                raise
            except (BusTimeout, BusUnavailable):  # (the process hosting the bus or the status went down
                continue  # with it: not yet back, or back in the middle of a node's handshake)
            st = next(s for s in status.services if s.name == "controller")
            if st.last.pid not in (0, before) and st.health == "ok":
                break
            await asyncio.sleep(0.2)
    port = cell.config.robot("r1").skill_port
    reader, writer = await asyncio.open_connection(cell.config.skills.host, port)
    try:
        async with asyncio.timeout(60):
            while True:  # (until the new controller has joined the bus: refused before, with the reason)
                writer.write(b"abcd0001:follow:pick\r\n")
                line = (await reader.readuntil(b"\r\n")).decode()
                if line.startswith("abcd0001:done:"):
                    break
                assert "no trajectory named" not in line, line
                await asyncio.sleep(0.5)
    finally:
        writer.close()
    x, y, z = (float(v) for v in line.split(":")[3].split(",")[:3])
    want = arm_model("ur5e").fk(goal)[0] * 1000
    assert np.abs(np.array([x, y, z]) - want).max() < 0.5, (line, want)
