"""Trajectories followed as planned (issue 55): TPs fitted to the plan at any point density, one
trajectory naming two robots' joints split across them and started together, Cartesian paths from
bags and CSV, and a plan the fitting refuses, on MuJoCo arms of a real cell through `cell follow`."""

from __future__ import annotations

import asyncio
import re
import time
from pathlib import Path

import numpy as np
import pytest

from cell.launcher import fetch_status
from cell.robot.arm import arm_model
from cell.trajectory.cartesian import Poses
from cell.trajectory.sources import Points, load, split_robots
from tests.conftest import free_port, run_cell
from tests.trajectory.test_follow import TS, joint_trajectory, write_message
from tests.trajectory.test_trajectory import Q0, UR

AMP = np.array([0.5, -0.3, 0.3, 0.4, 0.4, 0.6])


def out_and_back(pps: float, seconds: float, amp: np.ndarray = AMP) -> tuple[np.ndarray, np.ndarray]:
    t = np.linspace(0.0, seconds, round(pps * seconds) + 1)
    return t, Q0 + amp * (1 - np.cos(2 * np.pi * t / seconds))[:, None] / 2


def stamp(t: float) -> object:
    return TS.types["builtin_interfaces/msg/Time"](sec=int(t), nanosec=round(t % 1 * 1e9))


def pose(p: np.ndarray, xyzw=(1.0, 0.0, 0.0, 0.0)) -> object:
    T = TS.types
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=T["geometry_msgs/msg/Quaternion"](x=xyzw[0], y=xyzw[1], z=xyzw[2], w=xyzw[3]),
    )


def path_message(t: np.ndarray, positions: np.ndarray) -> object:
    """nav_msgs/Path: stamped poses, the tool pointing down (x 180 deg), as a Cartesian planner writes."""
    T = TS.types
    header = T["std_msgs/msg/Header"](stamp=stamp(0.0), frame_id="base")
    poses = [
        T["geometry_msgs/msg/PoseStamped"](
            header=T["std_msgs/msg/Header"](stamp=stamp(ti), frame_id="base"), pose=pose(p)
        )
        for ti, p in zip(t, positions, strict=True)
    ]
    return T["nav_msgs/msg/Path"](header=header, poses=poses)


def test_a_trajectory_of_two_robots_joints_is_split_by_their_prefixes() -> None:
    t, q = out_and_back(20, 1.0)
    names = [f"r1_{n}" for n in UR] + [f"left_{n}" for n in UR]
    both = Points(names, t, np.hstack([q, q + 0.1]), np.zeros((len(t), 12)), None, "", "dual", "bag")
    r1, r2 = split_robots(both, {"r1": "r1_", "r2": "left_"}) or []
    assert (r1.robot, r2.robot, r1.name, r1.joint_names) == ("r1", "r2", "dual:r1", UR)
    assert np.array_equal(r2.q, q + 0.1) and r2.qd is not None and r2.qd.shape == (len(t), 6)
    assert split_robots(Points(UR, t, q), {"r1": "r1_", "r2": "r2_"}) is None  # (one robot's)
    with pytest.raises(Exception, match=r"joint 'elbow_joint' is of none of the robots"):
        split_robots(Points([*names[:11], "elbow_joint"], t, np.hstack([q, q])), {"r1": "r1_", "r2": "left_"})


def test_cartesian_paths_are_read_from_bags_and_csv(tmp_path: Path) -> None:
    p0 = arm_model("ur5e").fk(Q0)[0]
    t = np.linspace(0.0, 2.0, 21)
    positions = p0 + np.outer(np.sin(np.pi * t / 2.0), [0.05, 0.05, 0.0])
    bag = write_message(tmp_path / "path", "/cartesian", path_message(t + 100.0, positions))
    (got,) = load(bag)
    assert isinstance(got, Poses) and got.t is not None and np.allclose(got.t, t)
    assert np.allclose(got.positions, positions) and got.rotations is not None
    assert np.allclose(got.rotations[0], np.diag([1.0, -1.0, -1.0]))
    T = TS.types
    header = T["std_msgs/msg/Header"](stamp=stamp(0.0), frame_id="base")
    array = T["geometry_msgs/msg/PoseArray"](header=header, poses=[pose(p) for p in positions])
    (untimed,) = load(write_message(tmp_path / "array", "/poses", array))
    assert isinstance(untimed, Poses) and untimed.t is None and len(untimed.positions) == 21
    csv = tmp_path / "square.csv"
    csv.write_text("x,y,z\n" + "\n".join(",".join(map(str, p)) for p in positions))
    (from_csv,) = load(csv)
    assert isinstance(from_csv, Poses) and from_csv.t is None and np.allclose(from_csv.positions, positions)
    stuck = path_message(np.array([0.0, 1.0, 1.0]), positions[:3])
    with pytest.raises(Exception, match=r"pose 2's stamp is not after the one before"):
        load(write_message(tmp_path / "stuck", "/cartesian", stuck))


def _errors(stdout: str, robot: str) -> tuple[float, float]:
    got = re.search(
        rf"{robot}: \d+ points over [\d.]+ s .* max ([\d.]+) mm \(t = [\d.]+ s\), median ([\d.]+) mm", stdout
    )
    assert got is not None, stdout
    return float(got.group(1)), float(got.group(2))


@pytest.mark.slow
async def test_plans_of_any_density_two_arms_and_a_cartesian_path_are_followed_as_planned(
    start_cell, tmp_path
) -> None:
    robots = [
        {"id": i, "name": f"r{i}", "skill_port": free_port(), "backend": "mujoco", "truth_hz": 500}
        for i in (1, 2)
    ]
    cell = await start_cell(run=["bus", "dataplane", "robots", "controller"], robots=robots)
    cfg = str(cell.path)

    async def follow(source: Path, *args: str):
        return await asyncio.to_thread(run_cell, "follow", str(source), "--config", cfg, *args, timeout=120)

    async def robots_heard() -> tuple[float, float]:
        """(uptime, missed ticks) of the robots service's latest heartbeat."""
        st = next(s for s in (await fetch_status(cell.config)).services if s.name == "robots").last
        return st.uptime_s, st.counters["missed_ticks"]

    async def missed_since(before: tuple[float, float], seconds: float) -> float:
        """Ticks the robots missed (the host held their process up) over the `seconds` after `before`:
        read from the first heartbeat that covers them."""
        async with asyncio.timeout(10):
            while (now := await robots_heard())[0] < before[0] + seconds:
                await asyncio.sleep(0.2)
        return now[1] - before[1]

    # the same out-and-back at 8, 40 and 250 points a second: within 0.5 mm at the points, 0.05 median.
    # A host that holds the arms' tick up (missed ticks) moves them off any plan: a follow it
    # disturbed, and only such a one, is run again (twice at most: a CI run once saw two follows in a
    # row lose 300 ticks each to the hypervisor's steal)
    for pps in (8, 40, 250):
        t, q = out_and_back(pps, 3.0)
        bag = write_message(tmp_path / f"d{pps}", "/planned", joint_trajectory(t, q, UR))
        for attempt in range(3):
            before, t0 = await robots_heard(), time.monotonic()
            done = await follow(bag, "--robot", "r1")
            assert done.returncode == 0, done.stderr[-2000:]
            worst, median = _errors(done.stdout, "r1")
            if worst <= 0.5 and median <= 0.05:
                break
            missed = await missed_since(before, time.monotonic() - t0)
            assert missed > 0 and attempt < 2, f"{missed} ticks missed meanwhile: {done.stdout}"
        fitted = re.search(
            r"TPs fitted to the plan: ([\d.]+) a second, the modelled tool within ([\d.]+) mm", done.stdout
        )
        assert fitted is not None and float(fitted.group(2)) <= 0.02 + 1e-4, done.stdout
    # one trajectory naming both arms' joints (a dual-arm MoveIt group), 20 points a second: split,
    # started together, both within the bounds
    t, q = out_and_back(20, 3.0)
    q2 = Q0 + np.array([-0.5, 0.3, -0.2, 0.4, -0.3, 0.6]) * (1 - np.cos(2 * np.pi * t / 3.0))[:, None] / 2
    names = [f"r1_{n}" for n in UR] + [f"r2_{n}" for n in UR]
    dual = write_message(tmp_path / "dual", "/planned", joint_trajectory(t, np.hstack([q, q2]), names))
    done = await follow(dual)
    assert done.returncode == 0, done.stderr[-2000:]
    for robot in ("r1", "r2"):
        worst, median = _errors(done.stdout, robot)
        assert worst <= 0.5 and median <= 0.05, done.stdout
    shift = re.search(r"start shift between robots: ([\d.]+) ms", done.stdout)
    assert shift is not None and float(shift.group(1)) <= 1.0, done.stdout
    # a Cartesian path from a bag (nav_msgs/Path, timed by its stamps), through IK: within 1 mm
    p0 = arm_model("ur5e").fk(Q0)[0]
    ts = np.linspace(0.0, 3.0, 61)
    positions = p0 + np.outer((1 - np.cos(np.pi * ts / 3.0)) / 2, [0.08, -0.05, 0.04])
    cart = write_message(tmp_path / "cart", "/cartesian", path_message(ts, positions))
    done = await follow(cart, "--robot", "r1")
    assert done.returncode == 0, done.stderr[-2000:]
    worst, _ = _errors(done.stdout, "r1")
    assert worst <= 1.0, done.stdout
    # and untimed (a PoseArray, back to the start and out again): ruckig times it within the joints'
    # limits at --speed
    T = TS.types
    header = T["std_msgs/msg/Header"](stamp=stamp(0.0), frame_id="base")
    array = T["geometry_msgs/msg/PoseArray"](header=header, poses=[pose(x) for x in positions[::-20]])
    done = await follow(write_message(tmp_path / "array", "/poses", array), "--robot", "r1")
    assert done.returncode == 0, done.stderr[-2000:]
    worst, _ = _errors(done.stdout, "r1")
    assert worst <= 1.0, done.stdout
    # a plan past what one TP a command window can hold within follow_tolerance_mm: refused, with
    # where, and nothing moves
    t, q = out_and_back(250, 0.8, np.full(6, 0.15))
    fast = write_message(tmp_path / "fast", "/planned", joint_trajectory(t, q, UR))
    refused = await follow(fast, "--robot", "r1")
    assert refused.returncode == 2 and "turns too fast for one TP a command window" in refused.stderr, (
        refused.stdout + refused.stderr
    )


def test_an_untimed_cartesian_path_is_timed_by_ruckig_within_the_joints_limits() -> None:
    """Neither times nor a tool speed: each straight leg at rest at its ends, as fast as the planning
    limits allow its joints (the tool on the line all along)."""
    from cell.config import load_config
    from cell.robot.kinematics import Kinematics
    from cell.trajectory.cartesian import TrajectoryError, planning_limits, solve

    arm = arm_model("ur5e")
    kin = Kinematics(arm)
    p0 = arm.fk(Q0)[0]
    corners = np.array([p0 + d for d in ([0, 0, 0], [0.15, 0, 0], [0.15, 0.1, -0.05], [0, 0, 0])])
    cfg = load_config(overrides={"robots": [{"id": 1, "name": "r1", "skill_port": 1234}]})
    lim = planning_limits(cfg, "r1", 0.5)
    traj = solve(kin, Q0, Poses(corners), limits=lim)
    dt = np.diff(traj.t)
    qd = np.diff(traj.q, axis=0) / dt[:, None]
    qdd = np.diff(qd, axis=0) / dt[1:, None]
    assert np.all(np.abs(qd) <= lim.v_max * 1.02) and np.all(np.abs(qdd) <= lim.a_max * 1.1)
    # it uses them: some joint comes near its acceleration limit, and the tool near a corner stands
    assert np.abs(qdd).max() > 0.5 * lim.a_max.max()
    tool = np.array([arm.fk(q)[0] for q in traj.q])
    at = [0]
    for c in corners[1:]:  # (each corner after the one before: the path ends where it began)
        at.append(at[-1] + 1 + int(np.argmin(np.linalg.norm(tool[at[-1] + 1 :] - c, axis=1))))
    assert np.allclose(tool[at], corners, atol=1e-6) and at[-1] == len(tool) - 1
    for k in range(3):  # on the lines between the corners
        leg = tool[at[k] : at[k + 1] + 1] - corners[k]
        u = (corners[k + 1] - corners[k]) / np.linalg.norm(corners[k + 1] - corners[k])
        assert np.abs(leg - np.outer(leg @ u, u)).max() < 1e-6
    with pytest.raises(TrajectoryError, match=r"Cartesian poses need times or a maximum tool speed"):
        solve(kin, Q0, Poses(corners))  # (no limits given: nothing to time it with)
