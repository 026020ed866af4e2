"""The robots' ground truth as bus messages: each arm's RobotTruth (its joints, velocities, tool pose,
commanded velocities, stop, digital outputs) for the state a group's readers see after a tick.

Encoded in C where it builds (truthcodec.c: the tool pose's kinematics and the message's bytes in one call
per group, for the robots process publishes these at truth_hz whatever moves), else by protobuf from
Python, the reference the C is held to byte for byte (tests/robot/test_truthcodec.py)."""

from __future__ import annotations

import ctypes
import itertools
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from cell.native import NativeUnavailable, build
from cell.robot.native import mujoco_library
from cell.v1 import robot_pb2

if TYPE_CHECKING:
    from cell.robot.emulator import RobotGroup

SOURCE = Path(__file__).parent / "truthcodec.c"
TYPE_NAME = robot_pb2.RobotTruth.DESCRIPTOR.full_name
_I, _P = ctypes.c_int64, ctypes.c_void_p
_KINDS = (np.float64, np.float64, np.float64, np.bool_, np.uint64)  # q, qd, target, stopped, digital_out


class _Truth(ctypes.Structure):
    """truth_t of truthcodec.c."""

    _fields_ = [
        *((name, _I) for name in ("n", "dof", "site")),
        *((name, _P) for name in ("model", "data", "qpos", "site_xpos", "site_xmat")),
        *((name, _P) for name in ("kinematics", "mat2quat", "ids")),
    ]


def _lib() -> ctypes.CDLL:
    lib = build("robot-truthcodec", (SOURCE,))
    p = ctypes.POINTER(_Truth)
    lib.truth_encode.argtypes = [p, ctypes.c_uint64, ctypes.c_uint64, *([_P] * 5), _P, _I, _P]
    lib.truth_encode.restype = _I
    lib.truth_pose.argtypes, lib.truth_pose.restype = [p, _P, _P], None
    lib.truth_bound.argtypes, lib.truth_bound.restype = [_I], _I
    return lib


def python_truths(group: RobotGroup, t_ns: int) -> list[bytes]:
    """Each arm's RobotTruth for the group's state, by protobuf (the reference)."""
    out = []
    for row in range(group.n):
        q = group.q[row]
        out.append(
            robot_pb2.RobotTruth(
                robot_id=int(group.ids[row]),
                t_ns=t_ns,
                q=q,
                qd=group.qd[row],
                tool_pose=group.arm.tool_pose(q),
                target=group.target[row],
                stopped=bool(group.stopped[row]),
                tick=group.tick_no,
                digital_out=int(group.digital_out[row]),
            ).SerializeToString()
        )
    return out


class NativeTruths:
    """A group's truths encoded in C, on a scratch mjData of the group's arm model of its own."""

    def __init__(self, group: RobotGroup) -> None:
        self.lib = _lib()
        mj, arm = mujoco_library(), group.arm
        self._data = mujoco.MjData(arm.model)  # (the model's own scratch data is shared in the process)
        self._ids = np.ascontiguousarray(group.ids, np.int64)
        t = self.state = _Truth()
        t.n, t.dof, t.site = group.n, arm.dof, arm.tool_site
        t.model, t.data = arm.model._address, self._data._address
        t.qpos = self._data.qpos.ctypes.data
        t.site_xpos, t.site_xmat = self._data.site_xpos.ctypes.data, self._data.site_xmat.ctypes.data
        t.kinematics = ctypes.cast(mj.mj_kinematics, ctypes.c_void_p).value
        t.mat2quat = ctypes.cast(mj.mju_mat2Quat, ctypes.c_void_p).value
        t.ids = self._ids.ctypes.data
        self._ref = ctypes.byref(t)
        self._out = np.zeros(group.n * self.lib.truth_bound(arm.dof), np.uint8)
        self._ends = np.zeros(group.n, np.int64)
        self._out_ptr, self._ends_ptr = self._out.ctypes.data, self._ends.ctypes.data
        self._arrays: tuple[np.ndarray, ...] = ()
        self._keep: tuple[np.ndarray, ...] = ()
        self._ptrs: tuple[int, ...] = ()

    def _pointers(self, group: RobotGroup) -> tuple[int, ...]:
        """The group's arrays' addresses: looked up again when the group replaces them (as C's thread
        starts and ends), and read from a contiguous copy where one is not as C reads it."""
        arrays = (group.q, group.qd, group.target, group.stopped, group.digital_out)
        if self._arrays and all(a is b for a, b in zip(arrays, self._arrays, strict=True)):
            return self._ptrs
        as_c: tuple[np.ndarray, ...] = tuple(
            np.ascontiguousarray(a, k) for a, k in zip(arrays, _KINDS, strict=True)
        )
        self._arrays = arrays if all(a is b for a, b in zip(as_c, arrays, strict=True)) else ()
        self._keep, self._ptrs = as_c, tuple(a.ctypes.data for a in as_c)
        return self._ptrs

    def __call__(self, group: RobotGroup, t_ns: int) -> list[bytes]:
        q, qd, target, stopped, dout = self._pointers(group)
        out, ends = self._out, self._ends
        size = self.lib.truth_encode(
            self._ref,
            t_ns,
            group.tick_no,
            q,
            qd,
            target,
            stopped,
            dout,
            self._out_ptr,
            out.size,
            self._ends_ptr,
        )
        assert size >= 0, "the truth buffer is too small"  # (sized by truth_bound: never)
        raw = out[:size].tobytes()
        return [raw[a:b] for a, b in itertools.pairwise([0, *ends.tolist()])]

    def pose(self, q: np.ndarray) -> np.ndarray:
        """The tool pose C computes for q (arm.ArmModel.tool_pose's)."""
        q = np.ascontiguousarray(q, np.float64)
        pose = np.zeros(7)
        self.lib.truth_pose(self._ref, q.ctypes.data, pose.ctypes.data)
        return pose


def truths_for(group: RobotGroup) -> Callable[[RobotGroup, int], list[bytes]]:
    """The group's truth encoder: C's where it builds, else protobuf's from Python."""
    try:
        return NativeTruths(group)
    except NativeUnavailable:
        return python_truths
