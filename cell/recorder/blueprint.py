"""The live view's layout (a Rerun blueprint), made for a robot cell rather than left to Rerun's guess.

Rerun's own guess is a grid with a view per entity root: the services' restart counters took as
much room as the arms.  Here the arms in 3D take the largest area (tool paths as trails, the active
TP marked, the planned TPs, the camera as a frustum where it stands), beside them each robot's
joints (position actual and planned, velocity actual and commanded), the data plane's time from
status to command, the camera's image and the event log; the health counters (data plane,
services, Responsive Link, the skill requests) sit in a second tab, out of the way until wanted.
"""

from __future__ import annotations

from collections.abc import Sequence

import rerun.blueprint as rrb


def robot_joints(robot: str) -> rrb.Vertical:
    """One robot's joints: position (actual, planned), velocity (actual, commanded)."""
    return rrb.Vertical(
        rrb.TimeSeriesView(origin=f"joints/{robot}/position", name=f"{robot}: joint position (rad)"),
        rrb.TimeSeriesView(origin=f"joints/{robot}/velocity", name=f"{robot}: velocity and command (rad/s)"),
        name=robot,
    )


def modular_robot() -> rrb.Vertical:
    """The modular robot's cycle: the tool against its reference, each cycle's A, B, C, D, guesses, and
    (on the SnP cycle) each module's clock against the master's."""
    return rrb.Vertical(
        rrb.TimeSeriesView(
            origin="modular", contents=["modular/tool_error_mm"], name="modular: tool error (mm)"
        ),
        rrb.TimeSeriesView(origin="modular/cycle_us", name="modular: A, B, C, D a cycle (us)"),
        rrb.TimeSeriesView(origin="modular/guessed", name="modular: messages guessed, per module"),
        rrb.TimeSeriesView(origin="modular/clock_offset_us", name="modular: module clocks - master's (us)"),
        name="modular",
    )


def cell_blueprint(robots: Sequence[str], camera: bool = True, modular: bool = False) -> rrb.Blueprint:
    """The cell's view: `robots` by name; camera: the vision service runs (its image has a place);
    modular: the modular robot runs (drawn beside the arms, its cycle in a tab of its own)."""
    tabs = [*(robot_joints(r) for r in robots), *([modular_robot()] if modular else [])]
    side: list[rrb.Container | rrb.View] = [
        rrb.Tabs(*tabs, name="joints") if tabs else rrb.Vertical(name="joints"),
        rrb.TimeSeriesView(
            origin="dataplane",
            contents=[f"dataplane/{k}_{p}_us" for k in ("answer", "batch") for p in ("p50", "p99")],
            name="data plane: status -> command (us, p50 / p99: at the robots; a batch in user space)",
        ),
    ]
    if camera:
        side.append(rrb.Spatial2DView(origin="vision/camera", name="camera"))
    side.append(rrb.TextLogView(origin="events", name="events"))
    cell = rrb.Horizontal(
        rrb.Spatial3DView(
            origin="/", contents=["robots/**", *(["modular/**"] if modular else [])], name="cell"
        ),
        rrb.Vertical(*side, row_shares=[3, 1, 2, 2][: len(side)]),
        column_shares=[3, 2],
        name="cell",
    )
    health = rrb.Tabs(
        rrb.TimeSeriesView(
            origin="dataplane", contents=["dataplane/**", "- dataplane/drops/**"], name="data plane"
        ),
        rrb.TimeSeriesView(origin="dataplane/drops", name="data plane drops"),
        rrb.TimeSeriesView(origin="services", name="services"),
        rrb.TimeSeriesView(origin="rlink", name="Responsive Link"),
        rrb.Spatial2DView(origin="gantt", name="skill requests"),
        name="health",
    )
    return rrb.Blueprint(rrb.Tabs(cell, health, active_tab=0), collapse_panels=True)


def teleop_blueprint() -> rrb.Blueprint:
    """`cell teleop`'s view (cell.teleop.view): the two arms and the object in 3D, beside them the
    forces of both sides (the paper's Figs. 16-17: the local one reversed, so the curves lie on each
    other when the operator feels what the object does), the tips' heights and the run's log."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="teleop/world", name="local and remote arms"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="teleop/force", name="force z (N): remote, local reversed"),
                rrb.TimeSeriesView(origin="teleop/z", name="tip z (mm)"),
                rrb.TextLogView(origin="teleop/log", name="log"),
                row_shares=[2, 2, 1],
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )
