"""The Adept paper's application: find a close-range camera's focus plane with vision feedback.

The robot carries a calibration card on its tool flange, over a camera that
looks up at it (service `vision`).  The paper's coroutines are in
cell/vision/focus.py: `init_move` brings the robot home and then to the
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

from cell.vision.focus import ufloop  # the paper's init_move, move_tool_z and ufloop

DELTA_Z = float(os.environ.get("DELTA_Z", "2.0"))  # mm per increment
SPEED = float(os.environ.get("APPR_SPEED", "25"))  # percent


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
