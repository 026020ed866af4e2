"""The robots' truth encoded in C (cell/robot/truthcodec.c) against protobuf's own encoding of the same
RobotTruth, byte for byte, and its tool pose against the arm model's."""

from __future__ import annotations

import numpy as np
import pytest

from cell.config import load_config
from cell.robot import udp
from cell.robot.emulator import RobotGroup
from cell.robot.truthcodec import NativeTruths, python_truths
from cell.v1 import robot_pb2
from tests.conftest import cell_overrides


@pytest.fixture(params=[("kinematic", 1), ("mujoco", 1), ("kinematic", 3), ("mujoco", 3)], ids=str)
def group(request):
    sink = udp.open_socket("127.0.0.1")
    host, port = sink.getsockname()
    robots = [
        {"id": 7 + i, "name": f"t{i}", "skill_port": 3000 + i, "backend": request.param[0], "truth_hz": 0}
        for i in range(request.param[1])
    ]
    cfg = load_config(overrides={**cell_overrides(), "robots": robots})
    g = RobotGroup(cfg.robots, f"{host}:{port}")
    yield g
    g.close()
    sink.close()


def _scramble(g: RobotGroup, rng: np.random.Generator) -> None:
    """A state with what protobuf leaves out (zeros, -0.0, an unset flag) beside what it writes."""
    for a in (g.q, g.qd, g.target):
        a[:] = rng.uniform(-3, 3, a.shape)
        a[rng.random(a.shape) < 0.2] = 0.0
        a[rng.random(a.shape) < 0.1] = -0.0
    g.stopped[:] = rng.random(g.n) < 0.5
    g.digital_out[:] = rng.integers(0, 2**18, g.n) * (rng.random(g.n) < 0.7)
    g.tick_no = int(rng.integers(0, 2**40)) * int(rng.random() < 0.9)


def test_the_c_truth_is_protobufs_byte_for_byte(group: RobotGroup) -> None:
    native = NativeTruths(group)  # (a C encoder that does not build is a failure)
    rng = np.random.default_rng(7)
    for k in range(300):
        _scramble(group, rng)
        t_ns = int(rng.integers(0, 2**63)) if k % 10 else 0
        got, want = native(group, t_ns), python_truths(group, t_ns)
        assert got == want, k
    tick = group.tick_no
    group.stopped[:], group.digital_out[:], group.tick_no = True, 2**64 - 1, 2**64 - 1  # (the longest)
    assert native(group, 2**64 - 1) == python_truths(group, 2**64 - 1)
    msg = robot_pb2.RobotTruth.FromString(got[-1])  # (and it reads back as what it says)
    assert msg.robot_id == 6 + group.n and list(msg.q) == group.q[-1].tolist() and msg.tick == tick


def test_its_tool_pose_is_the_arm_models(group: RobotGroup) -> None:
    native = NativeTruths(group)
    rng = np.random.default_rng(3)
    lim = group.arm.limits
    for _ in range(100):
        q = rng.uniform(lim.q_min, lim.q_max)
        assert np.array_equal(native.pose(q), group.arm.tool_pose(q))


def test_it_follows_the_arrays_the_group_replaces(group: RobotGroup) -> None:
    """C's thread gives the group new arrays as it starts (run_native): the encoder reads those."""
    native = NativeTruths(group)
    group.tick_no = 5
    assert native(group, 1) == python_truths(group, 1)
    group.q = group.q.copy() + 0.25
    group.qd = np.asfortranarray(group.qd)  # (not as C reads it: read through a copy)
    assert native(group, 2) == python_truths(group, 2)
    group.q += 0.5  # (the same array, changed in place)
    assert native(group, 3) == python_truths(group, 3)
