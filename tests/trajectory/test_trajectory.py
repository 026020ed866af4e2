"""Trajectories planned elsewhere: the type and its checks (no sockets), the TP sections on its points,
and a MuJoCo arm of a real cell following one through the data plane."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from cell.bus import Bus
from cell.cellproc import robots_heard
from cell.controller.controller import Controller
from cell.controller.loop import LoopModel
from cell.controller.plan import PlanError
from cell.controller.tps import cut
from cell.robot.arm import arm_model
from cell.robot.kinematics import Kinematics
from cell.robot.pose import rotation_error
from cell.robot.truth import Truth
from cell.trajectory.cartesian import Poses, solve
from cell.trajectory.model import TimedMotion, Trajectory, TrajectoryError, joint_order, spline_velocities
from tests.conftest import free_port

Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
UR = [
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
]
JOINTS = arm_model("ur5e").joints


def wave(points: int, seconds: float, amp: np.ndarray | None = None) -> Trajectory:
    """Every joint out and back on 1 - cos, at rest at both ends: positions only, as planners give."""
    t = np.linspace(0.0, seconds, points)
    a = np.array([0.6, -0.4, 0.3, 0.5, 0.4, 0.8]) if amp is None else amp
    return Trajectory.build(t, Q0 + a * ((1 - np.cos(2 * np.pi * t / seconds)) / 2)[:, None], name="wave")


def test_joint_names_map_to_the_robots_joints_in_any_order_and_with_a_prefix() -> None:
    assert joint_order(UR, JOINTS) == [0, 1, 2, 3, 4, 5]
    assert joint_order([f"ur5e_{n}" for n in reversed(UR)], JOINTS) == [5, 4, 3, 2, 1, 0]
    assert joint_order(["j2", "j1", "elbow", "wrist_1", "wrist_2", "wrist_3"], JOINTS) == [1, 0, 2, 3, 4, 5]
    with pytest.raises(TrajectoryError, match="'knee_joint' is not one of this robot's"):
        joint_order([*UR[:5], "knee_joint"], JOINTS)
    with pytest.raises(TrajectoryError, match="do not name each"):
        joint_order([*UR[:5], UR[0]], JOINTS)
    # columns named in another order are put in the robot's
    q = np.arange(12.0).reshape(2, 6) / 10
    traj = Trajectory.build([0, 1], q[:, ::-1], joint_names=list(reversed(UR)), robot_joints=JOINTS)
    assert np.array_equal(traj.q, q)


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (
            lambda t, q: (t, np.where(np.arange(q.size).reshape(q.shape) == 20, np.nan, q)),
            "point 3: positions not a finite",
        ),
        (
            lambda t, q: (np.r_[t[:5], t[4], t[6:]], q),
            r"point 5: time 0\.3\d+ s does not come after point 4's",
        ),
        (lambda t, q: (t[:1], q[:1]), "at least 2 points"),
        (lambda t, q: (t, q[:, :5]), "5 joints per point for a robot of 6"),
    ],
)
def test_a_trajectory_that_cannot_be_one_is_refused_naming_the_point(change, words: str) -> None:
    base = wave(50, 4.0)
    lim = arm_model("ur5e").limits
    with pytest.raises(TrajectoryError, match=words):
        t, q = change(base.t, base.q)
        Trajectory.build(t, q).check(lim.q_min, lim.q_max, lim.v_max, lim.a_max)


def test_the_first_point_beyond_a_limit_is_named() -> None:
    lim = arm_model("ur5e").limits
    fast = wave(50, 0.6)  # the same wave in 0.6 s: too fast for the joints
    with pytest.raises(
        TrajectoryError, match=r"point \d+ \(t = 0\.\d+ s\): joint \d (velocity|acceleration)"
    ):
        fast.check(lim.q_min, lim.q_max, lim.v_max, lim.a_max)
    far = wave(50, 4.0, amp=np.array([0, 0, 0, 0, 0, 9.0]))  # wrist 3 past its range
    with pytest.raises(TrajectoryError, match=r"point \d+ .*joint 6 position"):
        far.check(lim.q_min, lim.q_max, np.full(6, 100.0), np.full(6, 100.0))
    slow = wave(50, 4.0)
    given = Trajectory.build(slow.t, slow.q, qdd=np.full_like(slow.q, 50.0))  # (accelerations given: checked)
    with pytest.raises(TrajectoryError, match=r"point 0 \(t = 0\.000 s\): joint 1 acceleration 50"):
        given.check(lim.q_min, lim.q_max, lim.v_max, lim.a_max)
    wave(50, 4.0).check(lim.q_min, lim.q_max, lim.v_max, lim.a_max)  # the slow one is fine


def test_missing_velocities_come_from_the_spline_and_the_motion_passes_through_every_point() -> None:
    t = np.linspace(0, 2 * np.pi, 120)
    v = spline_velocities(t, (1 - np.cos(t))[:, None])
    assert np.abs(v[3:-3, 0] - np.sin(t[3:-3])).max() < 1e-5 and v[0, 0] == v[-1, 0] == 0.0
    traj = wave(40, 4.0)
    motion = TimedMotion(traj)
    q, qd = motion.sample(traj.t)
    assert np.allclose(q, traj.q, atol=1e-12) and np.allclose(qd, motion.qd, atol=1e-9)
    mid = (traj.t[:-1] + traj.t[1:]) / 2  # between points: close to the curve the points came from
    exact = (
        Q0 + np.array([0.6, -0.4, 0.3, 0.5, 0.4, 0.8]) * ((1 - np.cos(2 * np.pi * mid / 4.0)) / 2)[:, None]
    )
    assert np.abs(motion.sample(mid)[0] - exact).max() < 1e-4


def test_a_cartesian_path_goes_straight_between_waypoints_and_names_what_it_cannot_reach() -> None:
    kin = Kinematics()
    p0, r0 = kin.fk(Q0)
    corners = np.array([p0 + d for d in ([0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0], [0, 0, 0])])
    traj = solve(kin, Q0, Poses(corners, max_speed=0.1), rate_hz=50)
    tool = np.array([kin.fk(q)[0] for q in traj.q])
    # every point on the square's edges (straight lines, not a joint spline's arcs), orientation kept
    off_edge = np.minimum(np.abs(tool[:, 0] - p0[0]), np.abs(tool[:, 0] - p0[0] - 0.1))
    off_edge = np.minimum(off_edge, np.minimum(np.abs(tool[:, 1] - p0[1]), np.abs(tool[:, 1] - p0[1] - 0.1)))
    assert off_edge.max() < 1e-6 and np.abs(tool[:, 2] - p0[2]).max() < 1e-6
    assert max(np.abs(rotation_error(kin.fk(q)[1], r0)).max() for q in traj.q) < 1e-6
    # 1 - cos between corners at 0.1 m/s top: each edge takes pi/2 s, the tool's speed peaks at the limit
    assert traj.duration == pytest.approx(4 * np.pi / 2 * 0.1 / 0.1, rel=1e-9)
    speed = np.linalg.norm(np.diff(tool, axis=0), axis=1) / np.diff(traj.t)
    assert 0.095 < speed.max() <= 0.1 + 1e-6
    at_corners = [int(np.argmin(np.abs(traj.t - k * np.pi / 2))) for k in range(5)]
    assert np.allclose(tool[at_corners], corners, atol=1e-7)
    with pytest.raises(
        TrajectoryError, match=r"^waypoint 1 \(1500\.0, 0\.0, 500\.0 mm\): no joint positions reach"
    ):
        solve(kin, Q0, Poses(np.array([p0, [1.5, 0.0, 0.5]]), max_speed=0.1))
    with pytest.raises(TrajectoryError, match="times or a maximum tool speed"):
        solve(kin, Q0, Poses(corners))
    timed = solve(kin, Q0, Poses(corners, t=np.arange(5.0)))  # with times: the poses are the points
    assert timed.points == 5 and np.allclose([kin.fk(q)[0] for q in timed.q], corners, atol=1e-7)


def test_tp_sections_end_on_the_points_when_they_are_no_denser_than_the_tps() -> None:
    lim = arm_model("ur5e").limits
    loop = LoopModel(np.full(6, 0.5), np.full(6, 30.0), lim.v_max, lim.a_max)
    sparse = wave(9, 4.0)  # a point every 0.5 s: each an end, the gaps split to about 0.1 s
    sections = cut(TimedMotion(sparse), 10.0, np.full(6, 60.0), loop)
    assert set(np.round(sparse.t[1:], 6)) <= set(np.round(sections.t_end, 6))
    assert np.diff(np.r_[0, sections.t_end]).max() <= 0.125 + 0.002  # (ends on the 2 ms status grid)
    dense = wave(1001, 4.0)  # every 4 ms: sections of about 0.1 s, each ending on a point
    sections = cut(TimedMotion(dense), 10.0, np.full(6, 60.0), loop)
    assert np.isin(np.round(sections.t_end, 6), np.round(dense.t, 6)).all()
    lengths = np.diff(np.r_[0, sections.t_end])
    assert (
        lengths.min() >= 0.05 - 1e-9
        and np.median(lengths) == pytest.approx(0.1)
        and sections.t_end[-1] == 4.0
    )


async def path_error_mm(truth: Truth, kin: Kinematics, res, traj: Trajectory) -> np.ndarray:
    """The tool's distance from the trajectory at each of its points, mm, from ground truth."""
    await truth.until("r1", res.end_ns + 10_000_000)
    q_real = truth.at("r1", res.t0_ns + traj.t * 1e9)
    return np.array(
        [np.linalg.norm(kin.fk(a)[0] - kin.fk(b)[0]) * 1000 for a, b in zip(q_real, traj.q, strict=True)]
    )


@pytest.mark.slow
async def test_a_mujoco_arm_follows_a_trajectory_within_the_cells_own_accuracy(start_cell) -> None:
    robots = [{"id": 1, "name": "r1", "skill_port": free_port(), "backend": "mujoco", "truth_hz": 500}]
    cell = await start_cell(run=["bus", "dataplane", "robots"], robots=robots)
    kin = Kinematics()
    async with Bus.connect(cell.config.bus, "test") as bus, Controller(bus, cell.config) as ctl:
        truth = Truth()
        async with asyncio.TaskGroup() as tg:
            watcher = tg.create_task(truth.run(bus))
            await robots_heard(ctl, {1})
            # refused before anything is loaded: the robot stays where it is
            with pytest.raises(PlanError, match=r"robot 1: trajectory 'wave': point \d+ \(t = "):
                await ctl.follow({"r1": wave(40, 0.5)})
            await ctl.move_joints("r1", Q0 + 0.2)  # away from the start: brought there first
            traj = wave(40, 4.0)
            res = await ctl.follow({"r1": traj})
            assert res.t0_ns > res.start_ns  # (the approach)
            err = await path_error_mm(truth, kin, res, traj)
            assert err.max() <= 1.0 and np.median(err) <= 0.1, (err.max(), np.median(err))
            # onto a trajectory on the fly: a slow move under way is switched (TrajectorySwitcher), the
            # trajectory starts long before the move would have ended, and is followed as accurately
            move = await ctl.move_joints("r1", Q0 + 0.5, speed=0.1, wait=False)
            await truth.until("r1", move.start_ns + 300_000_000)
            other = wave(40, 4.0, amp=np.array([-0.3, 0.2, -0.2, 0.3, 0.3, -0.5]))
            res = await ctl.follow({"r1": other}, speed=0.5, replace=True)
            assert res.start_ns < move.end_ns - 1_000_000_000 and ctl.engine.last_switch is not None
            err = await path_error_mm(truth, kin, res, other)
            assert err.max() <= 1.0 and np.median(err) <= 0.1, (err.max(), np.median(err))
            watcher.cancel()
