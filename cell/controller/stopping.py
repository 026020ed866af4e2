"""The controller's stops and losses: protective stops planned from where each robot is, the
publication of each plan, and the loss of a track's TPs.  One of the controller's parts, beside its
engine (cell.controller.engine), which calls on it, and its robot book (cell.controller.robots),
whose tracks it ends."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Sequence

import numpy as np

from cell.bus import Bus
from cell.controller.link import Link
from cell.controller.motion import MotionResult, Segment, Track
from cell.controller.plan import MotionLimits
from cell.controller.robots import RobotBook
from cell.controller.schedule import (
    STOP_MARGIN_NS,
    StopPlan,
    concat,
    status_of,
    stop_limits,
    stop_plan,
)
from cell.dataplane.client import DataplaneClient
from cell.v1 import controller_pb2, dataplane_pb2

log = logging.getLogger("cell.controller")


class Stopping:
    """Stops, plans published, losses, on the tracks of `book`; every update that sets registers or
    flushes holds `loading` (shared with the engine)."""

    def __init__(
        self, bus: Bus, dp: DataplaneClient, link: Link, book: RobotBook, loading: asyncio.Lock
    ) -> None:
        self.bus, self.dp, self.link, self.book, self.loading = bus, dp, link, book, loading
        self.lost: list[tuple[float, str]] = []  # (monotonic s, reason) of each loss, for the record
        self.stop_plan_ns = 5_000_000  # how long planning a stop takes (measured, pessimistic)
        self.late_stops = 0  # stops in place after the command window they were planned for began

    async def halt(self, track: Track) -> None:
        """Stop streaming the track's motion; wait for its updates in flight."""
        if track.moving:
            assert track.task is not None  # (moving: its task runs)
            track.task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await track.task
        if track.inflight:
            await asyncio.gather(*track.inflight, return_exceptions=True)

    def publish_plan(self, track: Track, seg: Segment) -> None:
        """The segment's plan on plan/<robot>, one message per robot of the track."""
        s = seg.sections
        # (led TPs: the robot is on each a window after its section's end)
        ends = np.rint((s.t_end + s.lead_s) * 1e9).astype(np.int64)
        t = np.concatenate([[seg.start_ns], seg.start_ns + ends])
        q0, v0 = seg.motion.sample(np.array([0.0]))
        q = np.vstack([q0, s.q])
        v = np.vstack([v0, s.q_plan_v])
        col = 0
        for rid in track.robots:
            n = self.book.arm_of(rid).dof
            cols = slice(col, col + n)
            col += n
            robot = self.book.robots.get(rid)
            if robot is None:
                continue
            msg = controller_pb2.Plan(
                robot_id=rid,
                joints=n,
                t_ns=t.tolist(),
                positions=q[:, cols].ravel().tolist(),
                velocities=v[:, cols].ravel().tolist(),
            )
            self.bus.publish(f"plan/{robot.name}", msg)

    # --- stops and losses ------------------------------------------------------------------------

    async def stop(
        self, robots: Sequence[int | str] | None = None, flush: bool = False
    ) -> dict[int, MotionResult]:
        """Protective stop: the robots decelerate within their limits from where they are, taking
        effect at the data plane's next packet after this update (within one command window).  With
        flush, every TP of these robots goes first, also those this controller did not load."""
        if robots is None:
            tracks = list(self.book.tracks.values())
        else:
            tracks = list({id(t): t for t in map(self.book.track, robots)}.values())
        for t in tracks:
            await self.halt(t)
        st = await self.link.state(
            sorted({r for t in tracks for r in t.robots}) if robots is not None else ()
        )
        by_id = {r.robot_id: r for r in st.robots}
        stops = self._plan_stops(tracks, by_id)
        batches, registers, remove, results, modelled = [], [], [], {}, {}
        for t, stop in stops:
            seg = stop.segment
            batches.append(stop.batch)
            registers.append(stop.register)
            remove += [(t.robot, i) for i in t.loaded]
            t.loaded, t.segment, t.q_hold = [int(i) for i in stop.batch.id], seg, seg.sections.q[-1].copy()
            t.stop_reason, t.epoch = t.stop_reason or "the robot was stopped", t.epoch + 1
            self.publish_plan(t, seg)
            results[t.robot] = MotionResult(seg.start_ns, seg.end_ns, seg.sections.q[-1].copy())
            modelled[t.robot] = stop.modelled
        flushed = sorted({r for t in tracks for r in t.robots}) if flush else []
        if flushed:
            remove = []
        if batches or flushed:
            insert = concat(batches) if batches else ()
            async with self.loading:
                reply = await self.dp.update(insert=insert, remove=remove, registers=registers, flush=flushed)
                for t in tracks:
                    t.loads += 1
            for rid, r in results.items():
                if not modelled[rid]:
                    r.start_ns = reply.now_ns  # in effect from the data plane's next packet on
                    continue
                track = self.book.track(rid)
                assert track.segment is not None  # (its stop's, set above)
                if reply.now_ns > self._last_status_ns(track, track.segment):
                    self.late_stops += 1  # it brakes a window later than its plan
                    log.warning(
                        "stop of robot %s in place %.1f ms into the window it was planned for",
                        rid,
                        (reply.now_ns - r.start_ns) / 1e6,
                    )
                r.start_ns = max(r.start_ns, reply.now_ns)
            for t in tracks:
                t.loaded_ns = reply.now_ns
        return results

    def _plan_stops(
        self, tracks: list[Track], by_id: dict[int, dataplane_pb2.RobotPlaneState]
    ) -> list[tuple[Track, StopPlan]]:
        """The tracks' stops, planned for when the update reaches the data plane: after the planning
        (measured) and half a round trip.  A stop planned from the loop model must be in place
        before the last status of its first window; planning that overran it is done again for
        the next window (a stop a window late would brake a window after its plan)."""
        todo = [(t, s) for t in tracks if (s := status_of(t, by_id)) is not None]
        todo = [(t, s) for t, s in todo if not any(r in self.book.stopped for r in t.robots)]
        stops: list[tuple[Track, StopPlan]] = []
        for _attempt in range(3):
            t0 = time.perf_counter_ns()
            now = self.link.now()
            apply_ns = now + self.stop_plan_ns * len(todo) + self.link.rtt_ns // 2 + STOP_MARGIN_NS
            stops = [
                (t, stop_plan(t, s, now, apply_ns, self.stop_limits(t), self.book.gain, self.book.loop(t)))
                for t, s in todo
            ]
            took = (time.perf_counter_ns() - t0) // max(1, len(todo))
            self.stop_plan_ns = max(took, int(0.7 * self.stop_plan_ns + 0.3 * took))
            arrive = self.link.now() + self.link.rtt_ns // 2 + STOP_MARGIN_NS
            if all(not p.modelled or arrive <= self._last_status_ns(t, p.segment) for t, p in stops):
                break
        return stops

    def _last_status_ns(self, track: Track, seg: Segment) -> int:
        """When the last status of the window a segment starts in is due."""
        loop = self.book.loop(track)
        return seg.start_ns + round((loop.window - 1) * loop.status_s * 1e9)

    def stop_limits(self, track: Track) -> MotionLimits:
        """A stop brakes with the drives' full deceleration, reached at once (they limit no jerk)."""
        return stop_limits(
            track.limits, np.concatenate([self.book.arm_of(r).limits.a_max for r in track.robots])
        )

    def lose(self, tracks: list[Track], reason: str) -> None:
        """The tables no longer hold these tracks' TPs: end their motions (MotionStopped(reason) to
        whoever waits), forget what was loaded, and plan the next motion from the measured state."""
        hit = [t for t in tracks if t.moving or t.loaded]
        for t in hit:
            t.stop_reason = reason
            t.generation += 1
            t.epoch += 1
            if t.moving:
                assert t.task is not None  # (moving: its task runs)
                t.task.cancel()
            t.loaded, t.segment, t.q_hold = [], None, None
        if hit:
            self.lost.append((time.monotonic(), reason))
            log.warning("%s (robots %s)", reason, sorted(r for t in hit for r in t.robots))
