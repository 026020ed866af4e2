"""The cell's run as a ROS 2 bag: a rosbag2 directory in MCAP storage, what `ros2 bag`, Foxglove
and PlotJuggler open, written with the pure-Python `rosbags` (no ROS installation).

Per robot <r> (joint names as ROS's ur_description has them, shoulder_pan_joint ...):
- /<r>/joint_states   sensor_msgs/msg/JointState: position and velocity, every status tick
- /<r>/joint_commands sensor_msgs/msg/JointState: the velocity the data plane commands, same ticks
- /<r>/planned        trajectory_msgs/msg/JointTrajectory: each plan the controller loads (its TPs)
- /<r>/tool_pose      geometry_msgs/msg/PoseStamped: the tool flange in <r>/base_link
and /tf (each <r>/base_link -> <r>/tool0), /tf_static (world -> each <r>/base_link, the robots
side by side as the Rerun view places them) and /rosout (rcl_interfaces/msg/Log: the cell's
events, worded as in the Rerun log).  Stamps and the bag's times are the cell clock (CLOCK_REALTIME).

Ground truth comes at the robots' full status rate while a bag is recorded (cell.robot.node
Publisher).  metadata.yaml is written when the recorder stops; a bag cut off by a crash has none
(`ros2 bag reindex` rebuilds it).  BagWriter takes decoded messages and knows no bus: `record`
feeds it from the bus.
"""

from __future__ import annotations

import asyncio
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from cell.models import get as get_model
from cell.recorder import base_position, each
from cell.recorder.cdr import Template
from cell.recorder.events import EVENT_TOPICS, Event, Events
from cell.service import ServiceContext
from cell.snp.state import realtime_offset_ns
from cell.v1 import controller_pb2, robot_pb2

if TYPE_CHECKING:
    from rosbags.typesys.store import Msg

JOINT_STATE = "sensor_msgs/msg/JointState"
JOINT_TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TF = "tf2_msgs/msg/TFMessage"
LOG = "rcl_interfaces/msg/Log"
LOG_LEVELS = {"INFO": 20, "WARN": 30, "ERROR": 40}  # rcl_interfaces/msg/Log's constants
_ZERO = QosTime(0, 0)
LATCHED = Qos(  # what /tf_static publishers offer: a late subscriber (or `ros2 bag play`) still gets it
    QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
    _ZERO, _ZERO, QosLiveliness.AUTOMATIC, _ZERO, False,
)  # fmt: skip


def set_aside(path: Path) -> Path | None:
    """An earlier bag at path moved to path.<its time> (None if there was none): never deleted, since
    it may be this very run's, written before the recorder restarted."""
    if not path.exists():
        return None
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(path.stat().st_mtime))
    kept, k = path.with_name(f"{path.name}.{stamp}"), 0
    while kept.exists():
        k += 1
        kept = path.with_name(f"{path.name}.{stamp}.{k}")
    path.rename(kept)
    return kept


@dataclass(frozen=True)
class BagRobot:
    id: int
    name: str
    joints: tuple[str, ...]  # ROS joint names


class BagWriter:
    """Decoded cell messages in, CDR-serialised ROS 2 messages out (see the module's docstring)."""

    def __init__(self, path: str | Path, robots: Sequence[BagRobot], offset_ns: int) -> None:
        self.path = Path(path)
        self.kept = set_aside(self.path)  # (rosbags writes only into a new directory)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.offset = offset_ns
        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        t = self.ts.types
        self.Time, self.Duration, self.Header = (
            t["builtin_interfaces/msg/Time"], t["builtin_interfaces/msg/Duration"], t["std_msgs/msg/Header"]
        )  # fmt: skip
        self.JointState, self.Log = t[JOINT_STATE], t[LOG]
        self.JointTrajectory, self.Point = t[JOINT_TRAJECTORY], t["trajectory_msgs/msg/JointTrajectoryPoint"]
        self.Pose, self.PoseStamped = t["geometry_msgs/msg/Pose"], t[POSE_STAMPED]
        self.Point3, self.Quaternion = t["geometry_msgs/msg/Point"], t["geometry_msgs/msg/Quaternion"]
        self.Vector3, self.Transform = t["geometry_msgs/msg/Vector3"], t["geometry_msgs/msg/Transform"]
        self.TransformStamped, self.TFMessage = t["geometry_msgs/msg/TransformStamped"], t[TF]
        self.robots = {r.id: r for r in robots}
        self.templates: dict[int, dict[str, Template]] = {}
        self.counts: Counter[str] = Counter()
        self.writer = Writer(self.path, version=8, storage_plugin=StoragePlugin.MCAP)
        self.writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)  # MCAP's zstd chunks
        self.writer.open()
        add = self.writer.add_connection
        self.conns = {}
        for r in robots:
            for topic, kind in (
                ("joint_states", JOINT_STATE),
                ("joint_commands", JOINT_STATE),
                ("planned", JOINT_TRAJECTORY),
                ("tool_pose", POSE_STAMPED),
            ):
                self.conns[f"/{r.name}/{topic}"] = add(f"/{r.name}/{topic}", kind, typestore=self.ts)
        self.conns["/tf"] = add("/tf", TF, typestore=self.ts)
        self.conns["/tf_static"] = add("/tf_static", TF, typestore=self.ts, offered_qos_profiles=[LATCHED])
        self.conns["/rosout"] = add("/rosout", LOG, typestore=self.ts)
        self._empty = np.zeros(0)

    # --- stamps -------------------------------------------------------------------------------------

    def stamp(self, t_mono_ns: int) -> tuple[int, Msg]:
        """The cell-clock time of a CLOCK_MONOTONIC instant: ns, and as builtin_interfaces/msg/Time."""
        t = t_mono_ns + self.offset
        return t, self.Time(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000)

    def write(self, topic: str, t_ns: int, msg: object, msgtype: str) -> None:
        self.raw(topic, t_ns, self.ts.serialize_cdr(msg, msgtype))

    def raw(self, topic: str, t_ns: int, data: bytes | memoryview) -> None:
        self.writer.write(self.conns[topic], t_ns, data)
        self.counts[topic] += 1

    # --- what the cell says ------------------------------------------------------------------------

    def start(self, t_mono_ns: int) -> None:
        """/tf_static: world -> each robot's base_link, once."""
        t, stamp = self.stamp(t_mono_ns)
        n = len(self.robots)
        transforms: list[Msg] = [
            self._transform(stamp, "world", f"{r.name}/base_link", (*base_position(i, n), 0.0, 0.0, 0.0, 1.0))
            for i, r in enumerate(self.robots.values())
        ]
        self.write("/tf_static", t, self.TFMessage(transforms=transforms), TF)

    def truth(self, m: robot_pb2.RobotTruth) -> None:
        r = self.robots.get(m.robot_id)
        if r is None or len(m.q) != len(r.joints):
            return
        tpl = self.templates.get(r.id) or self._templates(r)
        t = m.t_ns + self.offset
        self.raw(f"/{r.name}/joint_states", t, tpl["joint_states"].fill(t, position=m.q, velocity=m.qd))
        self.raw(f"/{r.name}/joint_commands", t, tpl["joint_commands"].fill(t, velocity=m.target))
        if len(m.tool_pose) == 7:
            x, y, z, qw, qx, qy, qz = m.tool_pose
            pose = (x, y, z, qx, qy, qz, qw)  # geometry_msgs' order: position, then x y z w
            self.raw(f"/{r.name}/tool_pose", t, tpl["tool_pose"].fill(t, pose=pose))
            self.raw("/tf", t, tpl["tf"].fill(t, pose=pose))

    def _templates(self, r: BagRobot) -> dict[str, Template]:
        """The robot's per-tick messages as CDR templates (cell.recorder.cdr), made at its first."""
        n, names, base = len(r.joints), list(r.joints), f"{r.name}/base_link"
        ser, e = self.ts.serialize_cdr, self._empty

        def joint_state(v: dict, position: bool) -> memoryview:
            header = self.Header(stamp=v["stamp"], frame_id="")
            pos = v["position"] if position else e
            js = self.JointState(header=header, name=names, position=pos, velocity=v["velocity"], effort=e)
            return ser(js, JOINT_STATE)

        def pose(v: dict) -> Msg:
            x, y, z, qx, qy, qz, qw = v["pose"]
            return self.Pose(
                position=self.Point3(x=x, y=y, z=z), orientation=self.Quaternion(x=qx, y=qy, z=qz, w=qw)
            )

        def tool_pose(v: dict) -> memoryview:
            return ser(
                self.PoseStamped(header=self.Header(stamp=v["stamp"], frame_id=base), pose=pose(v)),
                POSE_STAMPED,
            )

        def tf(v: dict) -> memoryview:
            transform = self._transform(v["stamp"], base, f"{r.name}/tool0", v["pose"])
            return ser(self.TFMessage(transforms=[transform]), TF)

        T = self.Time
        self.templates[r.id] = tpl = {
            "joint_states": Template(lambda v: joint_state(v, True), {"position": n, "velocity": n}, T),
            "joint_commands": Template(lambda v: joint_state(v, False), {"velocity": n}, T),
            "tool_pose": Template(tool_pose, {"pose": 7}, T),
            "tf": Template(tf, {"pose": 7}, T),
        }
        return tpl

    def plan(self, p: controller_pb2.Plan) -> None:
        """A plan as the JointTrajectory it is: its TPs, times from its first."""
        r = self.robots.get(p.robot_id)
        if r is None or not p.t_ns or p.joints != len(r.joints):
            return
        t_ns = np.array(p.t_ns, np.int64)
        q = np.array(p.positions).reshape(-1, p.joints)
        v = np.array(p.velocities).reshape(-1, p.joints)
        t, stamp = self.stamp(int(t_ns[0]))
        points = []
        for k, dt in enumerate((t_ns - t_ns[0]).tolist()):
            points.append(
                self.Point(
                    positions=np.ascontiguousarray(q[k]),
                    velocities=np.ascontiguousarray(v[k]) if v.shape[0] == q.shape[0] else self._empty,
                    accelerations=self._empty,
                    effort=self._empty,
                    time_from_start=self.Duration(sec=dt // 1_000_000_000, nanosec=dt % 1_000_000_000),
                )
            )
        header = self.Header(stamp=stamp, frame_id=f"{r.name}/base_link")
        jt = self.JointTrajectory(header=header, joint_names=list(r.joints), points=points)
        self.write(f"/{r.name}/planned", t, jt, JOINT_TRAJECTORY)

    def log(self, ev: Event) -> None:
        t, stamp = self.stamp(ev.t_ns)
        name = "cell." + ev.source.replace("/", ".")
        msg = self.Log(
            stamp=stamp, level=LOG_LEVELS[ev.level], name=name, msg=ev.text, file="", function="", line=0
        )
        self.write("/rosout", t, msg, LOG)

    def close(self) -> None:
        """Writes metadata.yaml: the bag is complete."""
        self.writer.close()

    def _transform(self, stamp: Msg, parent: str, child: str, pose: Sequence[float]) -> Msg:
        """child in parent: pose is x, y, z, then the quaternion x, y, z, w (geometry_msgs' order)."""
        x, y, z, qx, qy, qz, qw = (float(v) for v in pose)
        return self.TransformStamped(
            header=self.Header(stamp=stamp, frame_id=parent),
            child_frame_id=child,
            transform=self.Transform(
                translation=self.Vector3(x=x, y=y, z=z), rotation=self.Quaternion(x=qx, y=qy, z=qz, w=qw)
            ),
        )


def bag_robots(config) -> list[BagRobot]:
    return [BagRobot(r.id, r.name, get_model(r.model).ros_joint_names) for r in config.robots]


async def record(ctx: ServiceContext, ready: Callable[[], None]) -> None:
    """Write [recorder] bag from the bus until cancelled; the bag is closed (complete) on the way out."""
    bus = ctx.bus
    truth = await bus.subscribe("truth/")
    plans = await bus.subscribe("plan/")
    events_sub = await bus.subscribe(*EVENT_TOPICS)
    bag = BagWriter(ctx.config.recorder.bag, bag_robots(ctx.config), realtime_offset_ns())
    bag.start(time.monotonic_ns())
    events = Events()
    ctx.log.info("recording a ROS 2 bag (MCAP) to %s", bag.path)
    if bag.kept is not None:
        ctx.log.info("the bag that was there is kept as %s", bag.kept)

    def counted() -> None:
        ctx.counters["bag_messages"] = bag.counts.total()

    def on_event(env) -> None:
        ev = events.describe(env)
        if ev is not None:
            bag.log(ev)

    try:
        async with asyncio.TaskGroup() as tg:
            tg.create_task(each(truth, lambda env: bag.truth(env.decode(robot_pb2.RobotTruth)), counted))
            tg.create_task(each(plans, lambda env: bag.plan(env.decode(controller_pb2.Plan))))
            tg.create_task(each(events_sub, on_event))
            ready()
    finally:
        bag.close()
        ctx.log.info("bag %s closed: %d messages", bag.path, bag.counts.total())


# --- reading one back (`cell bag info`) -------------------------------------------------------------


@dataclass(frozen=True)
class TopicInfo:
    topic: str
    msgtype: str
    count: int
    first_ns: int
    last_ns: int

    @property
    def rate_hz(self) -> float:
        span = self.last_ns - self.first_ns
        return (self.count - 1) / (span / 1e9) if self.count > 1 and span > 0 else 0.0


@dataclass(frozen=True)
class BagInfo:
    path: Path
    storage: str
    start_ns: int
    end_ns: int
    size_bytes: int
    topics: list[TopicInfo]

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9

    @property
    def messages(self) -> int:
        return sum(t.count for t in self.topics)


class BagError(Exception):
    """A bag that cannot be read: one line says why."""


def info(path: str | Path) -> BagInfo:
    """Topics, counts, times and rates of a rosbag2 bag (either storage), read with rosbags."""
    from rosbags.highlevel import AnyReader

    p = Path(path)
    if not p.exists():
        raise BagError(f"{p}: no such file or directory")
    bag = p if p.is_dir() else p.parent
    if not (bag / "metadata.yaml").exists() and any(bag.glob("*.mcap")):
        raise BagError(
            f"{bag}: no metadata.yaml (its recorder was cut off): `ros2 bag reindex {bag}` rebuilds it"
        )
    try:
        with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            first: dict[int, int] = {}
            last: dict[int, int] = {}
            counts: Counter[int] = Counter()
            for conn, t, _raw in reader.messages():
                first.setdefault(conn.id, t)
                last[conn.id] = t
                counts[conn.id] += 1
            topics = [
                TopicInfo(c.topic, c.msgtype, counts[c.id], first.get(c.id, 0), last.get(c.id, 0))
                for c in sorted(reader.connections, key=lambda c: c.topic)
            ]
            start, end = reader.start_time, reader.end_time
    except Exception as exc:  # rosbags raises its own errors per storage: one line says which
        raise BagError(f"{p}: not a readable ROS 2 bag ({type(exc).__name__}: {exc})") from None
    files = [f for f in bag.iterdir() if f.is_file()]
    kinds = {".mcap": "mcap", ".db3": "sqlite3"}
    storage = ", ".join(sorted({kinds[f.suffix] for f in files if f.suffix in kinds})) or "?"
    return BagInfo(bag, storage, start, end, sum(f.stat().st_size for f in files), topics)
