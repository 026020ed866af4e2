"""The controller's verdict on a silent data plane (cell/controller/supervision.py): a data plane that
stops answering ends the motions it carried; the controller's own process held up (a loaded host
holds it as long as it likes) is no silence of the data plane's."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import time
from collections.abc import AsyncIterator

import numpy as np
import pytest

from cell.controller.controller import Controller, MotionStopped
from cell.controller.supervision import DEAD_S, WATCH_S, supervise
from cell.launcher import fetch_status
from tests.controller.test_controller import Q0, driving, robots

SILENT = "the data plane stopped answering"


@contextlib.asynccontextmanager
async def supervised(start_cell) -> AsyncIterator[tuple[Controller, asyncio.Task]]:
    """A controller on a cell of one arm, its watch on the data plane on (as the service runs it), and
    a motion of a few seconds under way on r1 (its task)."""
    async with driving(start_cell, robots("kinematic")) as (ctl, _), asyncio.TaskGroup() as tg:
        watch = tg.create_task(supervise(ctl))
        async with asyncio.timeout(10):  # (its first answer: the take-over done)
            while ctl.engine.tables_ready is None or not ctl.engine.tables_ready.is_set():
                await asyncio.sleep(0.01)
        move = asyncio.create_task(ctl.move_joints("r1", Q0 + np.array([1.2, 0, 0, 0, 0, 0]), speed=0.2))
        async with asyncio.timeout(10):  # (under way: its TPs are in the tables)
            while not ctl.track("r1").loaded:
                await asyncio.sleep(0.01)
        await asyncio.sleep(2 * WATCH_S)  # (answers in since it began)
        try:
            yield ctl, move
        finally:
            watch.cancel()
            move.cancel()
            with contextlib.suppress(asyncio.CancelledError, MotionStopped):
                await move


def _verdicts(ctl: Controller) -> list[str]:
    return [why for _, why in ctl.stopping.lost if why.startswith(SILENT)]


@pytest.mark.slow
async def test_a_controller_held_up_longer_than_the_verdict_takes_no_silence_for_the_data_planes(
    start_cell,
) -> None:
    async with supervised(start_cell) as (ctl, _):
        assert ctl.track("r1").moving
        held_from = time.monotonic()
        time.sleep(DEAD_S + 3 * WATCH_S)  # noqa: ASYNC251  # this process held up, its event loop with it
        await asyncio.sleep(3 * WATCH_S)  # (the answers that came meanwhile, read)
        assert time.monotonic() - held_from >= DEAD_S + 3 * WATCH_S
        assert _verdicts(ctl) == []  # (a trajectory the hold-up let run dry is another matter)


@pytest.mark.slow
async def test_a_data_plane_silent_longer_than_the_verdict_loses_the_motions_it_carried(start_cell) -> None:
    async with supervised(start_cell) as (ctl, move):
        status = await fetch_status(ctl.config)
        pid = next(s for s in status.services if s.name == "dataplane").last.pid
        os.kill(pid, signal.SIGSTOP)  # the data plane hangs
        try:
            async with asyncio.timeout(DEAD_S + 1.0):
                while not _verdicts(ctl):
                    await asyncio.sleep(WATCH_S / 2)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
        with pytest.raises(MotionStopped, match=SILENT):
            await move


@pytest.mark.slow
async def test_a_silence_the_hypervisor_stole_is_no_verdict(
    start_cell, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Steal stops every vCPU of the VM, the data plane's too: a silence it explains is not the data
    plane's (this host's steal comes in bursts; faked here, as no test can make the hypervisor
    steal).  The motion goes on, or ends for what the data plane itself saw, never for the silence."""
    from cell import sched

    async with supervised(start_cell) as (ctl, _):
        status = await fetch_status(ctl.config)
        pid = next(s for s in status.services if s.name == "dataplane").last.pid
        monkeypatch.setattr(sched, "most_stolen", lambda before: 60.0)  # all of it stolen
        os.kill(pid, signal.SIGSTOP)
        try:
            await asyncio.sleep(DEAD_S + 5 * WATCH_S)
        finally:
            os.kill(pid, signal.SIGCONT)
        await asyncio.sleep(3 * WATCH_S)  # (its answers again)
        assert _verdicts(ctl) == [] and ctl.track("r1").stop_reason is None, ctl.stopping.lost
