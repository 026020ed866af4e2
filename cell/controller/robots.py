"""What the controller knows of its robots: their models (cell.models: limits, kinematics), the
closed loop their TPs drive, their tick grids (from their announcements), the track each is driven
on, and what holds them (a Responsive Link stop, a URScript program)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from typing import TypeVar

import numpy as np

from cell.bus import Bus, BusError, Subscription
from cell.config import CellConfig
from cell.controller.link import Link
from cell.controller.loop import LoopModel, trackable_accel
from cell.controller.motion import Segment, Track
from cell.controller.plan import MotionLimits
from cell.controller.schedule import Grid, grid_start, phase_at
from cell.controller.tps import Led, Sections, ToolError, cut, fit_led
from cell.robot.arm import ArmModel, arm_model
from cell.robot.kinematics import Kinematics
from cell.timer import realtime_offset
from cell.trajectory.motion import Motion
from cell.v1 import robot_pb2

_T = TypeVar("_T")
log = logging.getLogger("cell.controller")


@cache
def _kinematics(model: str) -> Kinematics:
    return Kinematics(arm_model(model))


class RobotBook:
    """The robots as the controller drives them: one of the controller's parts (its engine and its
    stopping read and write the tracks kept here)."""

    def __init__(self, bus: Bus, config: CellConfig, link: Link) -> None:
        self.bus, self.config, self.link = bus, config, link
        self.robots = {r.id: r for r in config.robots}
        self.tracks: dict[int, Track] = {}  # lead robot -> the track it (and robots merged with it) runs on
        # the TPs' gain (see cell.controller.tps): how far a TP lies ahead of where the robot should be
        self.gain = np.array(config.dataplane.c2) / np.array(config.dataplane.c1)
        # robots stopped over the Responsive Link, until released (-> when we heard it, monotonic s)
        self.stopped: dict[int, float] = {}
        self.programs: dict[int, str] = {}  # robots a URScript program holds (cell.ur): what holds them
        # robot -> its tick grid, from its announcements (see grid_start())
        self.grids: dict[int, Grid] = {}
        self._asked: set[int] = set()  # robots asked for their announcement (see know_grid())
        self._capped: set[int] = set()  # robots whose configured a_max was capped (warned once)
        # cut()'s one thread: not asyncio's pool of six, whose planners at once (a fleet launching
        # hundreds of motions) held the GIL from the event loop for 0.3 s at a time, and replies that
        # had come in milliseconds waited out their requests' timeouts unread
        self._planner = ThreadPoolExecutor(max_workers=1, thread_name_prefix="planner")

    def robot_id(self, robot: int | str) -> int:
        if isinstance(robot, int):
            return robot
        return self.config.robot(robot).id

    def track(self, robot: int | str) -> Track:
        """The track the robot is driven on (its own, made on first use, or a merged one's)."""
        rid = self.robot_id(robot)
        t = self.tracks.get(rid)  # (a track is kept under its lead robot: a fleet's thousand, looked up
        if t is not None and rid in t.robots:  # one by one in a scan per motion, were a tenth of its loop)
            return t
        for t in self.tracks.values():  # (a robot merged behind another's lead)
            if rid in t.robots:
                return t
        t = Track(rid, [rid], self.limits_of([rid]))
        self.tracks[rid] = t
        return t

    def model_of(self, robot: int) -> str:
        """The robot's model (config key `model`; robots not in the config: the defaults')."""
        r = self.robots.get(robot)
        return r.model if r is not None else self.config.robot_defaults.model

    def arm_of(self, robot: int) -> ArmModel:
        return arm_model(self.model_of(robot))

    def kinematics(self, robot: int) -> Kinematics:
        return _kinematics(self.model_of(robot))

    def limits_of(self, robots: list[int]) -> MotionLimits:
        """The joints' limits of robots moving as one: each robot's model's, capped by the data plane's
        v_max and the controller's a_max, side by side."""
        dpc, cc = self.config.dataplane, self.config.controller
        per = []
        for rid in robots:
            lim = self.arm_of(rid).limits
            n = lim.v_max.size
            a_max = np.minimum(lim.a_max, np.resize(np.array(cc.a_max), n))
            per.append(
                (
                    np.minimum(lim.v_max, np.resize(np.array(dpc.v_max), n)),
                    np.minimum(a_max, self._trackable_accel(rid, lim.a_max, a_max)),
                    np.resize(np.array(cc.j_max), n),
                )
            )
        return MotionLimits(
            v_max=np.concatenate([p[0] for p in per]),
            a_max=np.concatenate([p[1] for p in per]),
            j_max=np.concatenate([p[2] for p in per]),
            tool_v_max=cc.tool_v_max,
            tool_a_max=cc.tool_a_max,
            tool_j_max=cc.tool_j_max,
            tool_w_max=cc.tool_w_max,
        )

    def _trackable_accel(self, robot: int, drive: np.ndarray, asked: np.ndarray) -> np.ndarray:
        """The planned acceleration the robot's TPs can keep it on (cell.controller.loop's
        trackable_accel), with a warning, once per robot, where the configured controller.a_max asks
        for more."""
        status_hz, command_hz = self._rates(robot)
        window_s = (status_hz // command_hz) / status_hz
        bound = trackable_accel(drive, window_s, 1.0 / self.config.controller.tp_rate_hz)
        if np.any(asked > bound + 1e-9) and robot not in self._capped:
            self._capped.add(robot)
            log.warning(
                "robot %s: controller.a_max %s rad/s^2 capped to %s: with the drives' %s, a %.0f ms "
                "command window and %g TP/s the TPs cannot keep the robot on a plan that accelerates "
                "harder (docs/controller.md#planned-acceleration)",
                robot,
                np.round(asked, 2).tolist(),
                np.round(np.minimum(asked, bound), 2).tolist(),
                np.round(drive, 2).tolist(),
                window_s * 1e3,
                self.config.controller.tp_rate_hz,
            )
        return bound

    def _rates(self, robot: int) -> tuple[int, int]:
        """The robot's status and command rates (Hz); a robot not in the config: a UR's."""
        r = self.robots.get(robot)
        return (500, 125) if r is None else (r.status_hz, r.command_hz)

    def loop(self, track: Track) -> LoopModel:
        """The closed loop the track's TPs drive (cell.controller.loop)."""
        status_hz, command_hz = self._rates(track.robots[0])
        dpc, n = self.config.dataplane, track.joints
        return LoopModel(
            c1=np.resize(np.array(dpc.c1), n),
            c2=np.resize(np.array(dpc.c2), n),
            v_max=np.resize(np.array(dpc.v_max), n),
            a_max=np.concatenate([self.arm_of(r).limits.a_max for r in track.robots])[:n],
            status_s=1.0 / status_hz,
            window=status_hz // command_hz,
            n_bits=dpc.n_bits,
        )

    async def aside(self, job: Callable[[], _T]) -> _T:
        """job() in the book's planning thread (a cut: partial(book.cut, ...)), the loop free meanwhile."""
        return await asyncio.get_running_loop().run_in_executor(self._planner, job)

    def close(self) -> None:
        self._planner.shutdown(wait=False, cancel_futures=True)

    def cut(
        self,
        track: Track,
        motion: Motion,
        rate_hz: float,
        v0: np.ndarray | None = None,
        tick0: int = 0,
        held0: np.ndarray | None = None,
    ) -> Sections:
        """The motion cut into the track's TPs (cell.controller.tps.cut) with its robots' gain, fitted to
        their loop: 0.1-0.5 s of CPU for a long motion, so callers run it in a worker thread."""
        loop = self.loop(track)
        if isinstance(motion, Led):  # (a trajectory followed, a fine motion: TPs where the plan needs them)
            bound = self.config.controller.follow_tolerance_mm / 1e3
            return fit_led(motion, loop, rate_hz, self.tool_error(track), bound, v0, tick0, held0)
        gain = np.resize(self.gain, track.joints)
        return cut(motion, rate_hz, gain, loop, v0, tick0, held0)

    def tool_error(self, track: Track) -> ToolError:
        """How far each robot's tool is from the plan for joint deviations dq at plan positions q
        (the largest over the track's robots): through each arm's Jacobian, taken once at q, a
        window's rows at a time (the plan turns little in 8 ms)."""

        def at(q: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
            every, col = 4, 0
            jacobians = []  # (the columns of each robot, its Jacobians row by row)
            for rid in track.robots:
                arm = self.arm_of(rid)
                cols = slice(col, col + arm.dof)
                col += arm.dof
                jac = np.stack([arm.jacobian(x) for x in q[::every, cols]])  # (m / every, 3, dof)
                jacobians.append((cols, np.repeat(jac, every, axis=0)[: len(q)]))

            def error(dq: np.ndarray) -> np.ndarray:
                out = np.zeros(len(dq))
                for cols, jac in jacobians:
                    out = np.maximum(out, np.linalg.norm(np.einsum("mij,mj->mi", jac, dq[:, cols]), axis=1))
                return out

            return error

        return at

    async def follow_announcements(self, sub: Subscription) -> None:
        """Keep each robot's tick grid (RobotAnnounce.window_origin_ns) as robots (re)announce."""
        while True:
            try:
                batch = await sub.recv_batch()
            except BusError as exc:  # (the bus node is closing under us: the grids stay as they are)
                log.info("robot announcements no longer followed: %s", exc)
                return
            for env in batch:
                with contextlib.suppress(Exception):  # (a malformed one is the bus's to count)
                    self._take_announcement(env.decode(robot_pb2.RobotAnnounce))

    def _take_announcement(self, a: robot_pb2.RobotAnnounce) -> None:
        if a.window_origin_ns and a.status_hz and a.command_hz:
            w = max(1, a.status_hz // a.command_hz)
            self.grids[a.robot_id] = (a.window_origin_ns, round(1e9 / a.status_hz), w)

    async def know_grid(self, robot: int) -> None:
        """The robot's tick grid, asked of it once if no announcement has come yet (a controller
        that has just come up would otherwise start its first motions off the grid); a robot that
        does not answer within a second is driven without one."""
        if robot in self.grids or robot in self._asked:
            return
        self._asked.add(robot)
        r = self.robots.get(robot)
        if r is None:
            return
        with contextlib.suppress(BusError, ValueError):
            a = await self.bus.request(
                f"robot/{r.name}",
                "announce",
                robot_pb2.AnnounceRequest(),
                robot_pb2.RobotAnnounce,
                timeout=1.0,
            )
            self._take_announcement(a)

    def grid_start(self, robot: int, earliest_ns: int) -> tuple[int, int, int | None]:
        """schedule.grid_start on the robot's grid.  The grid is on the cell clock; the data plane says
        how its clock stands to that exactly (going through our own clock and the offset estimated
        over the bus is up to half a round trip off: a start a fraction of a period off the grid)."""
        rt = self.link.realtime_offset_ns
        if rt is None:
            rt = realtime_offset() - self.link.offset_ns
        return grid_start(self.grids.get(robot), earliest_ns, rt)

    def phase_at(self, seg: Segment, t_ns: int) -> int:
        return phase_at(self.grids.get(seg.robot), seg, t_ns)
