"""The Adept paper's focus-plane calibration coroutines (init_move, move_tool_z, ufloop).

The robot carries the calibration card on its tool flange, over a camera that
looks up at it.  `init_move` brings it home and then to the approach pose;
`ufloop` asks the camera for the card's sharpness, moves the tool one
`delta_z` towards the camera (SetSpeed + MoveToolZ, joined: three messages
sent at once), and repeats until the sharpness falls: the focus plane has
been passed, so the tool steps back one `delta_z`.  examples/focus_calibration.py
runs it; `cell bench skills` times its increments.
"""

from __future__ import annotations

from typing import Any

from cell.skills.client import Ack, MoveJoints, MoveRelTool, MoveToolZ, RobotClient, SetSpeed

HOME_DEG = (0.0, -90.0, 90.0, -90.0, -90.0, 0.0)  # the cell's start pose: the tool down, over the camera
APPROACH_MM = 60.0  # from home along the tool's z to the approach pose: a little short of the focus plane


async def init_move(rc: RobotClient) -> list[Ack]:
    return await rc.cmdexec(MoveJoints(HOME_DEG), MoveRelTool(0, 0, APPROACH_MM, 0, 0, 0))


async def move_tool_z(rc: RobotClient, appr_speed: float, delta_z: float) -> list[Ack]:
    return await rc.cmdexec_joined(SetSpeed(appr_speed), MoveToolZ(delta_z))


async def ufloop(
    cell: Any, rc: RobotClient, delta_z: float, appr_speed: float, limit: int = 60
) -> list[float]:
    """The sharpness after each increment, the last one lower than the one before (then stepped back)."""
    await init_move(rc)
    sharpness: list[float] = []
    while True:
        m = await cell.vision.request()
        if not m.found:
            raise RuntimeError(f"the camera does not see the calibration card: {m.reason}")
        sharpness.append(m.sharpness)
        # break the loop when the sharpness falls: the focus plane is behind us
        if len(sharpness) > 1 and sharpness[-1] < sharpness[-2]:
            break
        if len(sharpness) > limit:
            raise RuntimeError(f"no sharpness peak within {limit} increments")
        await move_tool_z(rc, appr_speed, delta_z)
    await move_tool_z(rc, appr_speed, -delta_z)  # retract back
    return sharpness
