"""The controller's watch on the data plane, for as long as the controller runs.

A data plane that stops answering, comes back with new (empty) tables, or drops a robot's
trajectory because the robot protective-stopped, ends the motions it carried, and so does another
controller taking a robot over: whoever waits on them gets MotionStopped with the reason at once,
and the next motion plans from where the robots are measured to stand.  The first answer is a
take-over: whatever an earlier controller left in the tables goes (robots in motion get a stop
planned from their status), and the robots are this controller's at the data plane from then on.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import TYPE_CHECKING

from cell import sched
from cell.bus import BusError
from cell.controller.schedule import dropped, taken
from cell.v1.dataplane_pb2 import DataplaneState

if TYPE_CHECKING:  # (the facade whose parts these work on; it imports this module)
    from cell.controller.controller import Controller

WATCH_S = 0.1  # how often supervise() reads the data plane's registers (a read each, in flight together)
DEAD_S = 0.5  # a data plane silent this long has lost the motions it carried (for us)
HELD_S = 0.05  # a wait of WATCH_S that ended this much later: this process was held up
# reads out at once at most: a lost one does not hold up the next, and a data plane slow to answer (a
# fleet's thousand robots in each state) is not asked faster than it answers
IN_FLIGHT = 2


async def supervise(ctl: Controller) -> None:
    """Watch the data plane; every loss of the tables, for whatever reason, ends the motions they
    carried and flushes what is left of them.

    A read goes out every WATCH_S whether or not the last one was answered (as BFD's probes do; up
    to IN_FLIGHT at once): the verdict is DEAD_S without any answer, never a few reads lost in a
    row (over a link that loses 5 % of its messages, two lost reads in a row in 4 s were a 15 %
    chance, each a false "lost")."""
    ctl.engine.tables_ready = ready = asyncio.Event()
    answers: asyncio.Queue[tuple[float, DataplaneState]] = asyncio.Queue()
    in_flight = asyncio.Semaphore(IN_FLIGHT)

    async def ask(asked: float) -> None:
        try:
            with contextlib.suppress(BusError):
                answers.put_nowait((asked, await ctl.link.state(timeout=DEAD_S)))
        finally:
            in_flight.release()

    async def probe() -> None:
        async with asyncio.TaskGroup() as reads:
            while True:
                await in_flight.acquire()
                reads.create_task(ask(time.monotonic()))
                await asyncio.sleep(WATCH_S)

    async with asyncio.TaskGroup() as tg:
        tg.create_task(probe(), name="supervise-probe")
        await _judge(ctl, ready, answers)


async def _judge(
    ctl: Controller, ready: asyncio.Event, answers: asyncio.Queue[tuple[float, DataplaneState]]
) -> None:
    """The answers in the order they were asked (an older one, overtaken, is no news), and the
    silence between them."""
    boot: int | None = None
    seen: dict[int, int] = {}  # robot -> the data plane's dropped_ns last seen
    owners: dict[int, int] = {}  # robot -> the controller the data plane last said it was
    # silence counts from the last answer (or our start): one slow answer is no verdict
    silent_since = newest = time.monotonic()
    stolen_at, excused = sched.stolen_seconds(), 0.0  # (the steal and our hold-ups since that answer)
    gone = False  # the motions were declared lost for silence; flush once it answers again
    while True:
        waited = time.monotonic()
        try:
            async with asyncio.timeout(WATCH_S):
                asked, st = await answers.get()
        except TimeoutError:
            now = time.monotonic()
            # time this process was held up (a loaded or stalled host: it woke late) is not the data
            # plane's silence: the answers that came meanwhile are still on their way in, behind this
            # timeout (a 0.5 s hold-up as ur_rtde's control interface started was once a false "lost")
            held = now - waited - WATCH_S
            if held > HELD_S:
                silent_since += held
                excused += held
            # ... nor is time the hypervisor stole of the VM's CPUs (nothing in it ran, the data plane
            # neither: a CI run at 25 % steal had a motion "lost" to a data plane that was fine).  What
            # cannot go on after it, the data plane ends itself: a robot's watchdog, an underrun
            if (
                not gone
                and now - silent_since >= DEAD_S
                and now - silent_since - max(0.0, sched.most_stolen(stolen_at) - excused) >= DEAD_S
            ):
                gone = True
                ready.clear()
                ctl.stopping.lose(
                    list(ctl.book.tracks.values()),
                    f"the data plane stopped answering ({now - silent_since:.1f} s): its motions are lost",
                )
            continue
        silent_since = time.monotonic()
        stolen_at, excused = sched.stolen_seconds(), 0.0
        if asked < newest:
            continue
        newest = asked
        ctl.engine.released(st, asked)
        if boot is None or st.boot_id != boot or gone:
            if boot is not None and st.boot_id != boot:
                ready.clear()
                ctl.stopping.lose(
                    list(ctl.book.tracks.values()), "the data plane restarted: its tables were lost"
                )
            with contextlib.suppress(BusError):
                # at our start robots may be moving on an earlier controller's TPs: stop them; after a
                # loss they went without commands and stand in a protective stop: hold them there
                # (a stop planned from the status registers of a data plane that just came back
                # could start from a status it had queued before it went away)
                await take_over(ctl, plan_stops=boot is None and not gone)
                boot, gone = st.boot_id, False
                seen = {r.robot_id: r.dropped_ns for r in st.robots}
                ready.set()
            newest = time.monotonic()  # (what was asked before the take-over is stale now)
            continue
        for track, why in dropped(st, seen, ctl.track):
            ctl.stopping.lose([track], why)
            ctl.engine.pending_flush.update({rid: track.loads for rid in track.robots})
        for track, why in taken(st, owners, ctl.id, ctl.track):  # (its tables are the other's now)
            ctl.stopping.lose([track], why)
        if ctl.engine.pending_flush:
            with contextlib.suppress(BusError):
                await flush_lost(ctl)


async def flush_lost(ctl: Controller) -> None:
    """Remove the TPs of lost motions from the tables, for the robots not loaded anew since."""
    async with ctl.loading:
        robots = sorted(r for r, loads in ctl.engine.pending_flush.items() if ctl.track(r).loads == loads)
        if robots:
            await ctl.dp.update(flush=robots)
        ctl.engine.pending_flush.clear()


async def take_over(ctl: Controller, plan_stops: bool = True) -> None:
    """Flush every configured robot's TPs (an earlier controller's, or a lost set); with plan_stops,
    stop the robots that are moving from their measured state, else they hold (commands of 0)."""
    robots = {r.id for r in ctl.config.robots} | {r for t in ctl.book.tracks.values() for r in t.robots}
    for t in ctl.book.tracks.values():
        await ctl.stopping.halt(t)
    if plan_stops:
        await ctl.stop(sorted(robots), flush=True)
        for t in ctl.book.tracks.values():  # what it stopped was an earlier controller's motion, not one
            t.stop_reason = None  # of ours: a first `break` finds the robot standing, not "stopped"
    else:
        async with ctl.loading:
            await ctl.dp.update(flush=sorted(robots))
