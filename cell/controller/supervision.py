"""The controller's watch on the data plane, for as long as the controller runs.

A data plane that stops answering, comes back with new (empty) tables, or drops a robot's
trajectory because the robot protective-stopped, ends the motions it carried: whoever waits on
them gets MotionStopped with the reason at once, and the next motion plans from where the robots
are measured to stand.  The first answer is a take-over: whatever an earlier controller left in the
tables goes (robots in motion get a stop planned from their status).
"""

from __future__ import annotations

import asyncio
import contextlib
import time

from cell.bus import BusError
from cell.controller.engine import Engine
from cell.controller.schedule import dropped

WATCH_S = 0.1  # how often supervise() reads the data plane's registers
DEAD_S = 0.5  # a data plane silent this long has lost the motions it carried (for us)
STATE_TIMEOUT_S = 0.25  # one read of its state: two unanswered in a row (with the pause) make DEAD_S


async def supervise(ctl: Engine) -> None:
    """Watch the data plane; every loss of the tables, for whatever reason, ends the motions they
    carried and flushes what is left of them."""
    ctl.tables_ready = ready = asyncio.Event()
    boot: int | None = None
    seen: dict[int, int] = {}  # robot -> the data plane's dropped_ns last seen
    # silence counts from the last answer (or our start): one slow answer is no verdict
    silent_since = time.monotonic()
    gone = False  # the motions were declared lost for silence; flush once it answers again
    while True:
        asked = time.monotonic()
        try:
            st = await ctl.link.state(timeout=STATE_TIMEOUT_S)
        except BusError:
            now = time.monotonic()
            if not gone and now - silent_since >= DEAD_S:
                gone = True
                ready.clear()
                ctl.lose(
                    list(ctl.tracks.values()),
                    f"the data plane stopped answering ({now - silent_since:.1f} s): its motions are lost",
                )
            await asyncio.sleep(WATCH_S)
            continue
        silent_since = time.monotonic()
        ctl.released(st, asked)
        if boot is None or st.boot_id != boot or gone:
            if boot is not None and st.boot_id != boot:
                ready.clear()
                ctl.lose(list(ctl.tracks.values()), "the data plane restarted: its tables were lost")
            with contextlib.suppress(BusError):
                # at our start robots may be moving on an earlier controller's TPs: stop them; after a
                # loss they went without commands and stand in a protective stop: hold them there
                # (a stop planned from the status registers of a data plane that just came back
                # could start from a status it had queued before it went away)
                await take_over(ctl, plan_stops=boot is None and not gone)
                boot, gone = st.boot_id, False
                seen = {r.robot_id: r.dropped_ns for r in st.robots}
                ready.set()
            await asyncio.sleep(WATCH_S)
            continue
        for track, why in dropped(st, seen, ctl.track):
            ctl.lose([track], why)
            ctl.pending_flush.update({rid: track.loads for rid in track.robots})
        if ctl.pending_flush:
            with contextlib.suppress(BusError):
                await flush_lost(ctl)
        await asyncio.sleep(WATCH_S)


async def flush_lost(ctl: Engine) -> None:
    """Remove the TPs of lost motions from the tables, for the robots not loaded anew since."""
    async with ctl.loading:
        robots = sorted(r for r, loads in ctl.pending_flush.items() if ctl.track(r).loads == loads)
        if robots:
            await ctl.dp.update(flush=robots)
        ctl.pending_flush.clear()


async def take_over(ctl: Engine, plan_stops: bool = True) -> None:
    """Flush every configured robot's TPs (an earlier controller's, or a lost set); with plan_stops,
    stop the robots that are moving from their measured state, else they hold (commands of 0)."""
    robots = {r.id for r in ctl.config.robots} | {r for t in ctl.tracks.values() for r in t.robots}
    for t in ctl.tracks.values():
        await ctl._halt(t)
    if plan_stops:
        await ctl.stop(sorted(robots), flush=True)
        for t in ctl.tracks.values():  # what it stopped was an earlier controller's motion, not one
            t.stop_reason = None  # of ours: a first `break` finds the robot standing, not "stopped"
    else:
        async with ctl.loading:
            await ctl.dp.update(flush=sorted(robots))
