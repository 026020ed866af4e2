"""The bilateral experiment live in Rerun: both arms, the object, forces of both sides, tip positions.

The sides stream their trace rows to the console (cell.teleop.realtime);
each chunk becomes columns of scalars at full rate (one send_columns per
series, on the timeline "teleop", in seconds from START) and one pose of
each arm drawn in 3D (the local arm at +y, the remote one at -y, as if side
by side on a bench).  The local force is drawn with its sign reversed, as in
the paper's Figs. 16-17.
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from cell.recorder.blueprint import teleop_blueprint
from cell.teleop.figures import C
from cell.teleop.model import HOME, L1, L2, OBJECTS, SHOULDER_Z, SURFACE_Z, TIP_RADIUS
from cell.teleop.wire import Role

TIMELINE = "teleop"
Y = {Role.LOCAL: 0.25, Role.REMOTE: -0.25}


def arm_points(q1: float, q2: float, y: float) -> np.ndarray:
    """Shoulder, elbow and tip in the world, from the two joint angles (hinges about +y)."""
    s = np.array([0.0, y, SHOULDER_Z])
    e = s + L1 * np.array([np.cos(q1), 0.0, -np.sin(q1)])
    t = e + L2 * np.array([np.cos(q1 + q2), 0.0, -np.sin(q1 + q2)])
    return np.stack([s, e, t])


class TeleopView:
    def __init__(self, rec: rr.RecordingStream, obj: str) -> None:
        self.rec = rec
        self.obj = OBJECTS[obj]
        rec.send_blueprint(teleop_blueprint())
        rec.log("teleop/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for role, y in Y.items():
            name = role.name.lower()
            rec.log(
                f"teleop/world/{name}/post",
                rr.LineStrips3D([[[0, y, 0], [0, y, SHOULDER_Z]]], radii=0.03, colors=[[80, 80, 90]]),
                static=True,
            )
        o = self.obj
        rec.log(
            "teleop/world/remote/table",
            rr.Boxes3D(
                centers=[[HOME[0], Y[Role.REMOTE], (SURFACE_Z - o.thickness) / 2]],
                half_sizes=[[0.08, 0.08, (SURFACE_Z - o.thickness) / 2]],
                colors=[[128, 128, 140]],
            ),
            static=True,
        )
        rec.log("teleop/force/remote", rr.SeriesLines(colors=[[220, 80, 40]], names="remote"), static=True)
        rec.log(
            "teleop/force/local_reversed",
            rr.SeriesLines(colors=[[40, 120, 220]], names="local (reversed)"),
            static=True,
        )
        rec.log("teleop/z/remote", rr.SeriesLines(colors=[[220, 80, 40]], names="remote"), static=True)
        rec.log("teleop/z/local", rr.SeriesLines(colors=[[40, 120, 220]], names="local"), static=True)

    def rows(self, role: Role, rows: np.ndarray) -> None:
        """A chunk of one side's trace rows."""
        if not len(rows):
            return
        rec, name = self.rec, role.name.lower()
        t = rows[:, C["t"]]
        index = [rr.TimeColumn(TIMELINE, duration=t)]
        fz = rows[:, C["fz"]] if role == Role.REMOTE else -rows[:, C["fz"]]
        force = "remote" if role == Role.REMOTE else "local_reversed"
        rec.send_columns(f"teleop/force/{force}", indexes=index, columns=rr.Scalars.columns(scalars=fz))
        rec.send_columns(
            f"teleop/z/{name}", indexes=index, columns=rr.Scalars.columns(scalars=rows[:, C["z"]] * 1e3)
        )
        last = rows[-1]
        rec.set_time(TIMELINE, duration=float(last[C["t"]]))
        pts = arm_points(last[C["q1"]], last[C["q2"]], Y[role])
        rec.log(f"teleop/world/{name}/arm", rr.LineStrips3D([pts], radii=[0.018], colors=[[50, 110, 200]]))
        rec.log(
            f"teleop/world/{name}/tip",
            rr.Points3D([pts[-1]], radii=[TIP_RADIUS], colors=[[230, 80, 50]]),
        )
        if role == Role.REMOTE:
            o, top = self.obj, SURFACE_Z - float(last[C["deflection"]])
            r, g, b, _ = o.rgba
            rec.log(
                "teleop/world/remote/object",
                rr.Boxes3D(
                    centers=[[HOME[0], Y[role], top - o.thickness / 2]],
                    half_sizes=[[0.05, 0.05, o.thickness / 2]],
                    colors=[[int(r * 255), int(g * 255), int(b * 255)]],
                ),
            )
        else:
            hand = float(last[C["hand_z"]])
            rec.log(
                "teleop/world/local/hand",
                rr.Points3D([[pts[-1][0], Y[role], hand]], radii=[0.012], colors=[[240, 190, 60]]),
            )

    def text(self, t: float, what: str, level: str = "INFO") -> None:
        self.rec.set_time(TIMELINE, duration=t)
        self.rec.log("teleop/log", rr.TextLog(what, level=level))
