"""Where trajectories come from: JSON and CSV files, and ROS 2 bags (rosbag2, MCAP or SQLite storage)
holding `trajectory_msgs/msg/JointTrajectory`, `control_msgs` FollowJointTrajectory goals or MoveIt's
`moveit_msgs/msg/DisplayTrajectory`, read with the pure-Python `rosbags` (no ROS installation).

Each source gives `Points`: raw, as the file has them (joint names not yet mapped to a robot's: the
cell does that, cell.trajectory.model.joint_order).  Anything that cannot be read is a TrajectoryError
with one line saying what and where.

JSON: {"trajectories": [{"robot": "r1", "name": "...", "joint_names": [...], "points": [{"t": 0.0,
"positions": [...], "velocities": [...], "accelerations": [...]}, ...]}, ...]} (or one such object
on its own; velocities and accelerations optional); or, a Cartesian path, "poses" instead of
"points" (cell.trajectory.cartesian: Poses, solved by IK once the robot's joints are known).
CSV: a header row `t,<joint>,...` (positions, rad), optionally `<joint>.vel` columns (rad/s); one
row a point.
"""

from __future__ import annotations

import csv
import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cell.trajectory.cartesian import Poses, quaternion_matrix
from cell.trajectory.model import MAX_POINTS, TrajectoryError

JOINT_TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"


@dataclass
class Points:
    joint_names: list[str]
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray | None = None
    qdd: np.ndarray | None = None
    robot: str = ""  # as the source names it ("": whichever robot the user says)
    name: str = ""
    source: str = field(default="", repr=False)


def split_robots(points: Points, prefixes: dict[str, str]) -> list[Points] | None:
    """A trajectory naming several robots' joints (a dual-arm MoveIt group: `r1_shoulder_pan_joint`,
    `r2_...`) as one per robot, its joints' names without the robot's prefix (prefixes: robot ->
    prefix; the longest that fits wins); None if its names are not of several robots.
    TrajectoryError for a name of none of them among names of several."""
    owner: list[str | None] = []
    for n in points.joint_names:
        fits = [r for r, p in prefixes.items() if n.startswith(p) and len(n) > len(p)]
        owner.append(max(fits, key=lambda r: len(prefixes[r])) if fits else None)
    robots = list(dict.fromkeys(r for r in owner if r is not None))
    if len(robots) < 2:
        return None
    if None in owner:
        stray = points.joint_names[owner.index(None)]
        raise TrajectoryError(
            f"{points.source}: joint {stray!r} is of none of the robots the other joints name "
            f"({', '.join(f'{r}: {prefixes[r]}*' for r in robots)})"
        )
    out = []
    for r in robots:
        cols = [i for i, o in enumerate(owner) if o == r]
        names = [points.joint_names[i][len(prefixes[r]) :] for i in cols]

        def part(a: np.ndarray | None, cols: list[int] = cols) -> np.ndarray | None:
            return None if a is None else a[:, cols]

        name = f"{points.name}:{r}" if points.name else r
        out.append(
            Points(
                names, points.t, points.q[:, cols], part(points.qd), part(points.qdd), r, name, points.source
            )
        )
    return out


def load(path: str | Path, topic: str | None = None, index: int | None = None) -> Sequence[Points | Poses]:
    """The trajectories in a file or bag (TrajectoryError naming what is wrong)."""
    p = Path(path)
    if not p.exists():
        raise TrajectoryError(f"{p}: no such file or directory")
    if p.is_dir() or p.suffix in (".mcap", ".db3"):
        return read_bag(p, topic, index)
    if p.suffix == ".json":
        return read_json(p)
    if p.suffix == ".csv":
        return read_csv(p)
    raise TrajectoryError(f"{p}: not a .json, .csv, .mcap, .db3 or rosbag2 directory")


def read_json(path: Path) -> list[Points | Poses]:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise TrajectoryError(f"{path}: not readable JSON ({exc})") from None
    entries = data.get("trajectories", [data]) if isinstance(data, dict) else None
    if not isinstance(entries, list) or not entries:
        raise TrajectoryError(f"{path}: no trajectories (see docs/trajectories.md for the format)")
    out: list[Points | Poses] = []
    for i, e in enumerate(entries):
        where = f"{path}: trajectory {i}"
        if isinstance(e, dict) and "poses" in e:
            out.append(_poses(e, where, str(path)))
            continue
        try:
            pts = e["points"]
            if len(pts) > MAX_POINTS:
                raise TrajectoryError(f"{where}: {len(pts)} points: at most {MAX_POINTS:,}")
            t = np.array([float(p["t"]) for p in pts])
            q = np.array([p["positions"] for p in pts], np.float64)
            qd = (
                np.array([p["velocities"] for p in pts], np.float64)
                if pts and "velocities" in pts[0]
                else None
            )
            qdd = (
                np.array([p["accelerations"] for p in pts], np.float64)
                if pts and "accelerations" in pts[0]
                else None
            )
            names = [str(n) for n in e.get("joint_names", [])]
        except (KeyError, TypeError, ValueError) as exc:
            raise TrajectoryError(f"{where}: {type(exc).__name__} {exc} (each point: t, positions)") from None
        out.append(Points(names, t, q, qd, qdd, str(e.get("robot", "")), str(e.get("name", "")), str(path)))
    return out


def _poses(e: dict, where: str, source: str) -> Poses:
    """A Cartesian path of a JSON file: {"poses": [{"position": [x, y, z] m, "orientation": [x, y, z,
    w] (optional), "t": s (optional)}, ...], "max_speed": m/s (when the poses have no t)}."""
    try:
        poses = e["poses"]
        if len(poses) > MAX_POINTS:
            raise TrajectoryError(f"{where}: {len(poses)} poses: at most {MAX_POINTS:,}")
        positions = np.array([p["position"] for p in poses], np.float64)
        with_t = [("t" in p) for p in poses]
        if any(with_t) and not all(with_t):
            raise TrajectoryError(f"{where}: some poses have a time t and some do not")
        t = np.array([float(p["t"]) for p in poses]) if poses and all(with_t) else None
        with_rot = [("orientation" in p) for p in poses]
        if any(with_rot) and not all(with_rot):
            raise TrajectoryError(f"{where}: some poses have an orientation and some do not")
        rots = (
            np.array([quaternion_matrix(p["orientation"]) for p in poses])
            if poses and all(with_rot)
            else None
        )
        speed = e.get("max_speed")
        max_speed = None if speed is None else float(speed)
    except (KeyError, TypeError, ValueError) as exc:
        raise TrajectoryError(
            f"{where}: {type(exc).__name__} {exc} (each pose: position, [orientation], [t])"
        ) from None
    return Poses(positions, rots, t, max_speed, str(e.get("robot", "")), str(e.get("name", "")), source)


def read_csv(path: Path) -> list[Points | Poses]:
    try:
        with path.open(newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise TrajectoryError(f"{path}: not readable CSV ({exc})") from None
    if len(rows) < 3:
        raise TrajectoryError(f"{path}: a header row and at least 2 points")
    if len(rows) - 1 > MAX_POINTS:
        raise TrajectoryError(f"{path}: {len(rows) - 1} points: at most {MAX_POINTS:,}")
    header = [h.strip() for h in rows[0]]
    if {"x", "y", "z"} <= set(header):
        return [_csv_poses(path, header, rows[1:])]
    if header[0] not in ("t", "time_from_start"):
        raise TrajectoryError(f"{path}: the first column must be t (s from the start), not {header[0]!r}")
    pos = [i for i, h in enumerate(header) if i > 0 and not h.endswith(".vel")]
    vel = {h.removesuffix(".vel"): i for i, h in enumerate(header) if h.endswith(".vel")}
    names = [header[i] for i in pos]
    try:
        table = np.array([[float(x) for x in r] for r in rows[1:]], np.float64)
    except ValueError as exc:
        raise TrajectoryError(f"{path}: {exc}") from None
    qd = None
    if vel:
        if set(vel) != set(names):
            raise TrajectoryError(f"{path}: velocity columns {sorted(vel)} for joints {names}")
        qd = table[:, [vel[n] for n in names]]
    return [Points(names, table[:, 0], table[:, pos], qd, None, "", path.stem, str(path))]


def _csv_poses(path: Path, header: list[str], rows: list[list[str]]) -> Poses:
    """A Cartesian path as CSV: columns x, y, z (m), optionally qx, qy, qz, qw (the tool's orientation)
    and t (s; without it a maximum tool speed times the path)."""
    try:
        table = np.array([[float(x) for x in r] for r in rows], np.float64)
    except ValueError as exc:
        raise TrajectoryError(f"{path}: {exc}") from None
    col = {h: i for i, h in enumerate(header)}
    rots = None
    if {"qx", "qy", "qz", "qw"} <= set(col):
        try:
            rots = np.stack(
                [quaternion_matrix(r[[col["qx"], col["qy"], col["qz"], col["qw"]]]) for r in table]
            )
        except TrajectoryError as exc:
            raise TrajectoryError(f"{path}: {exc}") from None
    t = table[:, col["t"]] if "t" in col else None
    return Poses(table[:, [col["x"], col["y"], col["z"]]], rots, t, None, "", path.stem, str(path))


# --- ROS 2 bags -------------------------------------------------------------------------------------


def _seconds(d: Any) -> float:  # (rosbags' messages: dataclasses made at run time, untyped)
    return float(d.sec) + float(d.nanosec) * 1e-9


def _from_message(msg: object) -> list[object]:
    """The JointTrajectory messages in a message, found by type through its fields: itself, a
    FollowJointTrajectory goal's (the goal, its SendGoal request, or the service event `ros2 bag
    record` takes of it), a DisplayTrajectory's RobotTrajectories.  Empty ones are left out (a goal
    with only a multi-DOF trajectory)."""
    found: list[object] = []

    def walk(obj: Any, depth: int) -> None:  # (a rosbags message, or one of its fields)
        if getattr(obj, "__msgtype__", "") == JOINT_TRAJECTORY:
            if obj.points:
                found.append(obj)
        elif depth and dataclasses.is_dataclass(obj):
            for f in dataclasses.fields(obj):
                v = getattr(obj, f.name)
                for item in v if isinstance(v, list) else (v,):
                    walk(item, depth - 1)

    walk(msg, 6)
    return found


def _cat(a: np.ndarray | None, b: np.ndarray | None, k: int) -> np.ndarray | None:
    return None if a is None or b is None else np.vstack([a, b[k:]])


def _joined(parts: list[Points]) -> list[Points]:
    """Consecutive segments of one joint group (a DisplayTrajectory's RobotTrajectories: MoveIt
    plans them to run one after the other, each timed from 0) as one trajectory; a segment's first
    point is dropped where it repeats the one before."""
    out: list[Points] = []
    for p in parts:
        prev = out[-1] if out else None
        if prev is None or prev.joint_names != p.joint_names or p.q.shape[1] != prev.q.shape[1]:
            out.append(p)
            continue
        same = p.t[0] == 0.0 and np.array_equal(p.q[0], prev.q[-1])
        k = 1 if same else 0
        t = np.concatenate([prev.t, prev.t[-1] + p.t[k:] - p.t[0] + (0.0 if same else 1e-3)])

        q, qd, qdd = np.vstack([prev.q, p.q[k:]]), _cat(prev.qd, p.qd, k), _cat(prev.qdd, p.qdd, k)
        out[-1] = Points(prev.joint_names, t, q, qd, qdd, prev.robot, prev.name, prev.source)
    return out


def _points(jt: Any, source: str, name: str) -> Points:  # (jt: a rosbags JointTrajectory, untyped)
    pts = jt.points
    if len(pts) > MAX_POINTS:
        raise TrajectoryError(f"{source}: {len(pts)} points: at most {MAX_POINTS:,}")
    names = list(jt.joint_names)
    t = np.array([_seconds(p.time_from_start) for p in pts])
    n = len(names)

    def column(attr: str) -> np.ndarray | None:
        rows = [np.asarray(getattr(p, attr), np.float64) for p in pts]
        if not rows or all(r.size == 0 for r in rows):
            return None
        bad = next((i for i, r in enumerate(rows) if r.size != n), None)
        if bad is not None:
            raise TrajectoryError(f"{source}: point {bad}: {rows[bad].size} {attr} for {n} joints")
        return np.vstack(rows)

    q = column("positions")
    if q is None:
        raise TrajectoryError(f"{source}: a JointTrajectory without positions")
    return Points(names, t, q, column("velocities"), column("accelerations"), "", name, source)


PATH, POSE_ARRAY = "nav_msgs/msg/Path", "geometry_msgs/msg/PoseArray"


def _bag_poses(msg: Any, msgtype: str, source: str, name: str) -> Poses:
    """A Cartesian path in a bag: nav_msgs/Path (timed by its poses' stamps, from the first; not timed
    where they are all alike) or geometry_msgs/PoseArray (not timed: a maximum tool speed times it)."""
    if msgtype == PATH:
        stamped = list(msg.poses)
        poses = [p.pose for p in stamped]
        stamps = np.array([_seconds(p.header.stamp) for p in stamped])
    else:
        poses, stamps = list(msg.poses), np.zeros(len(msg.poses))
    if len(poses) < 2:
        raise TrajectoryError(f"{source}: a path of {len(poses)} poses (2 at least)")
    if len(poses) > MAX_POINTS:
        raise TrajectoryError(f"{source}: {len(poses)} poses: at most {MAX_POINTS:,}")
    positions = np.array([[p.position.x, p.position.y, p.position.z] for p in poses], np.float64)
    try:
        rots = np.stack(
            [
                quaternion_matrix((p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w))
                for p in poses
            ]
        )
    except TrajectoryError as exc:
        raise TrajectoryError(f"{source}: {exc}") from None
    t = stamps - stamps[0] if np.ptp(stamps) > 0 else None
    if t is not None and np.any(np.diff(t) <= 0):
        k = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
        raise TrajectoryError(f"{source}: pose {k}'s stamp is not after the one before")
    return Poses(positions, rots, t, None, "", name, source)


def read_bag(path: Path, topic: str | None = None, index: int | None = None) -> list[Points | Poses]:
    """The trajectories of one message of a bag: the `index`-th (default: the last) on `topic` (default:
    the only topic of a trajectory type); a Cartesian path (nav_msgs/Path, geometry_msgs/PoseArray) as
    Poses, solved by the robot's IK once its joints are known."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    bag = path if path.is_dir() else path.parent
    try:
        reader = AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:  # (rosbags raises its own errors per storage: one line says which)
        raise TrajectoryError(f"{path}: not a readable ROS 2 bag ({type(exc).__name__}: {exc})") from None
    try:
        kinds = ("JointTrajectory", "FollowJointTrajectory", "DisplayTrajectory")
        wanted = [
            c
            for c in reader.connections
            if any(k in c.msgtype for k in kinds) or c.msgtype in (PATH, POSE_ARRAY)
        ]
        if topic is not None:
            wanted = [c for c in wanted if c.topic == topic]
        topics = sorted({c.topic for c in wanted})
        if not topics:
            have = ", ".join(sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})) or "none"
            what = f"topic {topic!r} of a trajectory type" if topic else "a topic of a trajectory type"
            raise TrajectoryError(f"{path}: no {what} (topics: {have})")
        if len(topics) > 1:
            raise TrajectoryError(f"{path}: trajectories on {', '.join(topics)}: choose one with --topic")
        try:
            raws = [(c, raw) for c, _t, raw in reader.messages(connections=wanted)]
        except Exception as exc:
            raise TrajectoryError(f"{path}: cannot read its messages ({type(exc).__name__}: {exc})") from None
        if not raws:
            raise TrajectoryError(f"{path}: no message on {topics[0]}")
        k = len(raws) - 1 if index is None else index
        if not -len(raws) <= k < len(raws):
            raise TrajectoryError(f"{path}: message {index} of {len(raws)} on {topics[0]}")
        conn, raw = raws[k]
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except Exception as exc:
            why = f"{type(exc).__name__}: {exc}"
            raise TrajectoryError(
                f"{path}: cannot decode {conn.msgtype} ({why}): is its type defined in the bag?"
            ) from None
        source = f"{path} {conn.topic} #{k % len(raws)}"
        if conn.msgtype in (PATH, POSE_ARRAY):
            return [_bag_poses(msg, conn.msgtype, source, f"{conn.topic}#{k % len(raws)}")]
        found = _from_message(msg)
        if not found:
            raise TrajectoryError(f"{path}: {conn.msgtype} holds no JointTrajectory")
        points = _joined([_points(jt, source, f"{conn.topic}#{k % len(raws)}") for jt in found])
        total = sum(p.t.size for p in points)
        if total > MAX_POINTS:
            raise TrajectoryError(f"{source}: {total} points: at most {MAX_POINTS:,}")
        return list(points)
    finally:
        reader.close()
