"""The Adept paper's application: find a close-range camera's focus plane with vision feedback.

The robot carries a calibration card on its tool flange, over a camera that
looks up at it (service `vision`).  `init_move` brings it home and then to the
approach pose; `ufloop` asks the camera for the card's sharpness, moves the
tool one `delta_z` towards the camera (SetSpeed + MoveToolZ, joined: three
messages sent at once), and repeats until the sharpness falls: the focus
plane has been passed, so the tool steps back one `delta_z`.

    cell run examples/focus_calibration.py --up

Prints, last, one JSON line: focus_error_mm (the card's final distance from
the lens, as the simulator knows it, minus the lens's focus distance),
delta_z_mm, increments, sharpness (the list, as in Fig. 9) and more.
"""

from __future__ import annotations

import json
import os

from cell.skills.client import MoveJoints, MoveRelTool, MoveToolZ, SetSpeed

HOME_DEG = [0.0, -90.0, 90.0, -90.0, -90.0, 0.0]  # the cell's start pose: the tool down, over the camera
APPROACH_MM = 60.0  # from home along the tool's z to the approach pose: a little short of the focus plane
DELTA_Z = float(os.environ.get("DELTA_Z", "2.0"))  # mm per increment
SPEED = float(os.environ.get("APPR_SPEED", "25"))  # percent


async def init_move(rc):
    return await rc.cmdexec(MoveJoints(tuple(HOME_DEG)), MoveRelTool(0, 0, APPROACH_MM, 0, 0, 0))


async def move_tool_z(rc, appr_speed, delta_z):
    return await rc.cmdexec_joined(SetSpeed(appr_speed), MoveToolZ(delta_z))


async def ufloop(cell, rc, delta_z, appr_speed, limit=60):
    await init_move(rc)
    sharpness = []
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


async def main(cell):
    info = await cell.vision.info()
    rc = cell.robot(info.robot)
    sharpness = await ufloop(cell, rc, DELTA_Z, SPEED)
    final = await cell.vision.request()  # a frame of the final pose (the pose xi_is)
    peak = max(range(len(sharpness)), key=sharpness.__getitem__)
    result = {
        "focus_error_mm": final.truth_distance_mm - info.focus_mm,
        "delta_z_mm": DELTA_Z,
        "increments": len(sharpness) - 1,
        "sharpness": [round(s, 2) for s in sharpness],
        "peak_index": peak,
        "final_distance_mm": final.truth_distance_mm,
        "focus_mm": info.focus_mm,
        "appr_speed": SPEED,
        "camera_frames_per_s": info.frames_per_s,
    }
    print(
        f"focus plane found {result['increments']} increments of {DELTA_Z} mm from the approach pose: "
        f"the card is {final.truth_distance_mm:.2f} mm from the lens, focused at {info.focus_mm:.0f} mm "
        f"(error {result['focus_error_mm']:+.2f} mm)"
    )
    print(json.dumps(result))
    return result
