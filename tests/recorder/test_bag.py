"""The run as a ROS 2 bag: CDR bytes identical to rosbags' own, a bag read back with rosbags (the
reader ROS users' tools agree with), `cell bag info`, and a bag's plans fed back to `cell follow`'s
reader.  The demo's bag (written by a whole cell) is checked in test_recorder's demo test."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML  # rosbags' own YAML reader

from cell.models import get as get_model
from cell.recorder.bag import BagError, BagRobot, BagWriter, info
from cell.recorder.cdr import Template
from cell.recorder.events import Event
from cell.trajectory.sources import load
from cell.v1 import controller_pb2, robot_pb2
from tests.conftest import cell_env

UR = get_model("ur5e").ros_joint_names
OFFSET = 1_700_000_000_000_000_000  # cell clock = monotonic + this
TS = get_typestore(Stores.ROS2_HUMBLE)


def truth(k: int, rid: int = 1) -> robot_pb2.RobotTruth:
    q = 0.1 * np.arange(6) + 0.001 * k
    return robot_pb2.RobotTruth(
        robot_id=rid, t_ns=1_000_000_000 + 2_000_000 * k, q=q, qd=-q, target=q / 2,
        tool_pose=[0.4, 0.1 * rid, 0.3 + 0.001 * k, 0.0, 1.0, 0.0, 0.0],
    )  # fmt: skip


def test_a_cdr_template_gives_rosbags_own_bytes_for_any_values() -> None:
    T, H, JS = (
        TS.types["builtin_interfaces/msg/Time"],
        TS.types["std_msgs/msg/Header"],
        TS.types["sensor_msgs/msg/JointState"],
    )

    def js(v: dict) -> bytes:
        header = H(stamp=v["stamp"], frame_id="")
        msg = JS(header=header, name=list(UR), position=v["p"], velocity=v["v"], effort=np.zeros(0))
        return TS.serialize_cdr(msg, "sensor_msgs/msg/JointState")

    tpl = Template(js, {"p": 6, "v": 6}, T)
    rng = np.random.default_rng(1)
    for t_ns in (0, 1_795_635_079_346_526_538, 999_999_999):
        p, v = rng.normal(size=6), rng.normal(size=6)
        stamp = T(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
        assert tpl.fill(t_ns, p=p, v=v) == bytes(js({"stamp": stamp, "p": p, "v": v}))
    try:
        tpl.fill(0, p=np.zeros(5), v=np.zeros(6))
    except ValueError as exc:
        assert "5 values for 6" in str(exc)
    else:
        raise AssertionError("a short array was written into the template")


def write_bag(path: Path) -> BagWriter:
    bag = BagWriter(path, [BagRobot(1, "r1", UR), BagRobot(2, "r2", UR)], OFFSET)
    bag.start(900_000_000)
    for k in range(500):  # one second at 500 Hz of each robot
        bag.truth(truth(k, 1))
        bag.truth(truth(k, 2))
    t = [1_000_000_000, 1_300_000_000, 1_800_000_000]
    q = np.array([[0.0] * 6, [0.1] * 6, [0.3] * 6])
    plan = controller_pb2.Plan(robot_id=1, joints=6, t_ns=t, positions=q.ravel(), velocities=(q / 2).ravel())
    bag.plan(plan)
    bag.log(Event(1_500_000_000, "r1: KIND_STOP a stop was ordered", "WARN", "robot/r1", None))
    bag.truth(robot_pb2.RobotTruth(robot_id=9, t_ns=1, q=[0.0] * 6))  # a robot it was not told of: skipped
    bag.close()
    return bag


def test_a_bag_holds_standard_messages_at_the_cells_clock_and_reads_back_with_rosbags(tmp_path) -> None:
    bag = write_bag(tmp_path / "run")
    meta = YAML(typ="safe").load((tmp_path / "run" / "metadata.yaml").read_text())[
        "rosbag2_bagfile_information"
    ]
    assert meta["storage_identifier"] == "mcap" and meta["version"] == 8
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    assert (
        {k: v for k, v in counts.items() if v} == dict(bag.counts)
        and counts["/r1/joint_states"] == 500
        and counts["/tf"] == 1000
    )
    assert counts["/r1/planned"] == 1 and counts.get("/r2/planned", 0) == 0 and counts["/rosout"] == 1
    with AnyReader([tmp_path / "run"], default_typestore=TS) as reader:
        seen: dict[str, list] = {}
        for conn, t, raw in reader.messages():
            seen.setdefault(conn.topic, []).append((t, reader.deserialize(raw, conn.msgtype)))
    t0, js = seen["/r1/joint_states"][7]
    assert t0 == OFFSET + 1_000_000_000 + 7 * 2_000_000  # the bag's time is the message's stamp
    assert js.header.stamp.sec * 10**9 + js.header.stamp.nanosec == t0
    assert list(js.name) == list(UR)
    assert np.allclose(js.position, truth(7).q) and np.allclose(js.velocity, truth(7).qd)
    cmd = seen["/r2/joint_commands"][7][1]
    assert np.allclose(cmd.velocity, truth(7, 2).target) and len(cmd.position) == 0
    pose = seen["/r2/tool_pose"][3][1]
    assert pose.header.frame_id == "r2/base_link"
    assert (pose.pose.position.y, pose.pose.orientation.x, pose.pose.orientation.w) == (0.2, 1.0, 0.0)
    frames = {(tf.header.frame_id, tf.child_frame_id) for _, m in seen["/tf"] for tf in m.transforms}
    assert frames == {("r1/base_link", "r1/tool0"), ("r2/base_link", "r2/tool0")}
    static = seen["/tf_static"][0][1].transforms
    placed = [(s.child_frame_id, s.transform.translation.y) for s in static]
    assert placed == [("r1/base_link", -0.6), ("r2/base_link", 0.6)]  # as the Rerun view places them
    plan = seen["/r1/planned"][0][1]
    times = [p.time_from_start.sec * 10**9 + p.time_from_start.nanosec for p in plan.points]
    assert times == [0, 300_000_000, 800_000_000]
    assert np.allclose(plan.points[2].positions, 0.3) and np.allclose(plan.points[2].velocities, 0.15)
    log = seen["/rosout"][0][1]
    assert (log.level, log.name, log.msg) == (30, "cell.robot.r1", "r1: KIND_STOP a stop was ordered")


def test_a_bag_already_there_is_kept_aside_never_deleted(tmp_path) -> None:
    """It may be this very run's, written before the recorder was restarted (or killed)."""
    first = write_bag(tmp_path / "run")
    second = write_bag(tmp_path / "run")
    third = write_bag(tmp_path / "run")
    assert first.kept is None and second.kept is not None and third.kept is not None
    assert second.kept != third.kept and second.kept.name.startswith("run.")
    for path in (second.kept, third.kept, tmp_path / "run"):
        with AnyReader([path], default_typestore=TS) as reader:
            assert reader.message_count == sum(first.counts.values())
    # one cut off (a recorder killed: no metadata.yaml) is said so, with the way to mend it
    (second.kept / "metadata.yaml").unlink()
    with pytest.raises(BagError, match=r"no metadata\.yaml \(its recorder was cut off\): `ros2 bag reindex "):
        info(second.kept)


def test_a_bags_plans_feed_back_to_cell_follow_and_cell_bag_info_reads_it(tmp_path) -> None:
    write_bag(tmp_path / "run")
    (pts,) = load(tmp_path / "run", topic="/r1/planned")
    assert list(pts.joint_names) == list(UR)
    assert np.allclose(pts.t, [0.0, 0.3, 0.8]) and np.allclose(pts.q[1], 0.1)
    out = subprocess.run(
        [sys.executable, "-m", "cell", "bag", "info", str(tmp_path / "run"), "--json"],
        env=cell_env(), capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    figures = json.loads(out.stdout.strip().splitlines()[-1])
    assert figures["storage"] == "mcap" and figures["messages"] == 4 * 1000 + 1 + 1 + 1
    assert abs(figures["topics"]["/r2/joint_states"]["rate_hz"] - 500.0) < 0.01
    assert figures["topics"]["/rosout"]["type"] == "rcl_interfaces/msg/Log"
    assert "/r1/joint_commands" in out.stdout and "500.0 Hz" in out.stdout
    # a bag cut short (its file truncated, no metadata) is one line and exit 2
    mcap = next((tmp_path / "run").glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:2000])
    bad = subprocess.run(
        [sys.executable, "-m", "cell", "bag", "info", str(tmp_path / "run")],
        env=cell_env(), capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert bad.returncode == 2 and bad.stderr.startswith("cell bag: ") and len(bad.stderr.splitlines()) == 1
    assert "not a readable ROS 2 bag" in bad.stderr
