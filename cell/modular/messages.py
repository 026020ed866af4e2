"""The modular robot as the bus carries it (proto/cell/v1/modular.proto): its status, answered to
`modular.status`, `plug` and `unplug`, and its state on `modular/state` for Rerun."""

from __future__ import annotations

import time

import numpy as np

from cell.modular.robot import ArmRobot
from cell.v1 import modular_pb2 as pb


def status(robot: ArmRobot, late: int) -> pb.ModularStatus:
    offsets = robot.clock_offsets_us
    return pb.ModularStatus(
        modules=[
            pb.ModuleStatus(name=n, state=str(s), guessed=int(g), where=w, clock_offset_us=float(o))
            for n, s, g, w, o in zip(
                robot.NAMES, robot.states, robot.guessed_by, robot.where, offsets, strict=True
            )
        ],
        cycles=robot.cycles,
        late_cycles=late,
        cycle_us_mean=robot.cycle_us_mean,
        cycle_us_max=robot.cycle_ns_max / 1e3,
        q=robot.q.tolist(),
        tool=robot.tool.tolist(),
        motion=robot.motion.path if robot.motion else "",
        stopped=robot.stopped,
        transport=robot.transport,
        period_ms=robot.period_ns / 1e6,
    )


def state(robot: ArmRobot, late: int) -> pb.ModularState:
    tool = robot.tool
    return pb.ModularState(
        t_ns=time.monotonic_ns(), q=robot.q.tolist(), tool=tool.tolist(), tool_ref=robot.tool_ref.tolist(),
        tool_error_mm=float(np.linalg.norm(tool - robot.tool_ref)) * 1e3, phase_us=robot.phase_us.tolist(),
        guessed=robot.guessed_by.tolist(), states=[str(s) for s in robot.states],
        frames=robot.frames().ravel().tolist(), late_cycles=late,
        clock_offset_us=robot.clock_offsets_us.tolist(), module_cycle_us=robot.module_cycle_us.tolist(),
    )  # fmt: skip
