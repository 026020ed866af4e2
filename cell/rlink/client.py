"""The cell's e-stop and state changes from any local process: a client of the hub's host interface.

`cell estop`, `await cell.estop()` in task scripts and the skill servers'
`estop` all come here.  An order goes out as one event packet per robot set
(cell.rlink.events), broadcast to every node through the hub, at once; the
call then waits, if asked, until every named robot has reported that it
stands still (or, for a resume, that it is released).  A robot that does not
report within the timeout is named in the TimeoutError.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import socket
import time
from collections.abc import Sequence
from typing import Self

from cell.config import CellConfig
from cell.rlink import events
from cell.rlink.cellnet import BROADCAST, Topology
from cell.rlink.events import EventError, RobotState
from cell.rlink.packet import EventType, Kind, Packet, PacketError, decode, encode

KEEPALIVE_S = 2.0  # a NOP this often keeps the client's lease at the hub (HOST_LEASE_S)
PRIORITY = {EventType.ESTOP: 3, EventType.STOP: 2, EventType.RESUME: 2, EventType.NOP: 0}


class EventClient:
    def __init__(self, config: CellConfig) -> None:
        topo = Topology(config.rlink)
        self.config = config
        self.hub = topo.address("hub")
        self.host = topo.host
        self.sock: socket.socket | None = None
        self._seq = random.randrange(256)
        self._waiters: dict[int, list[tuple[RobotState, asyncio.Future[float]]]] = {}
        self.reports: list[events.StateReport] = []  # every report heard, in order
        self._keepalive: asyncio.Task | None = None

    async def __aenter__(self) -> Self:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setblocking(False)
        # not connect()ed: a connected socket gets the ICMP error of a hub that is not up yet, and
        # uvloop then stops watching it for good (the reports piled up unread in the skill servers)
        s.bind((self.host[0], 0))
        self.sock = s
        asyncio.get_running_loop().add_reader(s.fileno(), self._read)
        self._send(EventType.NOP, self.hub, b"")  # the lease starts now: reports reach us from here on
        self._keepalive = asyncio.ensure_future(self._keep())
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._keepalive is not None:
            self._keepalive.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._keepalive
        if self.sock is not None:
            asyncio.get_running_loop().remove_reader(self.sock.fileno())
            self.sock.close()
            self.sock = None

    # --- orders ------------------------------------------------------------------------------

    def robot_ids(self, robots: Sequence[int | str] | None) -> list[int]:
        if robots is None or len(robots) == 0:
            return [r.id for r in self.config.robots]
        out = []
        for r in robots:
            if isinstance(r, int) or (isinstance(r, str) and r.isdigit()):
                out.append(int(r))
            else:
                out.append(self.config.robot(r).id)  # KeyError for an unknown name
        return out

    async def estop(
        self, robots: Sequence[int | str] | None = None, wait: bool = True, timeout: float = 5.0
    ) -> dict[int, float]:
        """Emergency stop; with wait, until every robot stands (ms from the order, per robot id; in a
        cell of several hosts, for the robots on the hub's host: the others stop on the data plane's
        stop ramp, and no node of theirs reports it)."""
        return await self._order(EventType.ESTOP, robots, RobotState.STILL, wait, timeout)

    async def stop(
        self, robots: Sequence[int | str] | None = None, wait: bool = True, timeout: float = 5.0
    ) -> dict[int, float]:
        """A stop on the data plane's ramp (the drives stay on); with wait, until they stand."""
        return await self._order(EventType.STOP, robots, RobotState.STILL, wait, timeout)

    async def resume(
        self, robots: Sequence[int | str] | None = None, wait: bool = True, timeout: float = 5.0
    ) -> dict[int, float]:
        """Release stopped robots; with wait, until each has reported it."""
        return await self._order(EventType.RESUME, robots, RobotState.RESUMED, wait, timeout)

    async def _order(
        self,
        type: EventType,
        robots: Sequence[int | str] | None,
        until: RobotState,
        wait: bool,
        timeout: float,
    ) -> dict[int, float]:
        ids = self.robot_ids(robots)
        loop = asyncio.get_running_loop()
        futs = {}
        if wait:
            reported = {r.id for r in self.config.rlink_robots()}  # (others are on a host without a node)
            for rid in (i for i in ids if i in reported):
                fut: asyncio.Future[float] = loop.create_future()
                self._waiters.setdefault(rid, []).append((until, fut))
                futs[rid] = fut
        t0 = time.monotonic()
        token = random.randrange(1 << 16)
        everyone = robots is None or len(robots) == 0
        for rs in events.robot_sets(None if everyone else ids, token):
            self._send(type, BROADCAST, rs.encode())
        if not wait:
            return {}
        try:
            _, late = await asyncio.wait(futs.values(), timeout=timeout)
        finally:
            for rid, fut in futs.items():
                fut.cancel()
                with contextlib.suppress(ValueError):
                    self._waiters[rid].remove((until, fut))
        if late:
            missing = sorted(rid for rid, f in futs.items() if f in late)
            raise TimeoutError(
                f"robot(s) {missing} did not report {until.name.lower()} within {timeout} s "
                "(is the robots service up?)"
            )
        return {rid: (f.result() - t0) * 1e3 for rid, f in futs.items()}

    # --- the socket --------------------------------------------------------------------------

    def _send(self, type: EventType, dst: int, payload: bytes) -> None:
        assert self.sock is not None
        p = Packet(Kind.EVENT, dst, self.hub, PRIORITY.get(type, 2), type, self._seq, payload)
        self._seq = (self._seq + 1) & 0xFF
        self.sock.sendto(encode(p), self.host)

    def _read(self) -> None:
        assert self.sock is not None
        while True:
            try:
                raw, addr = self.sock.recvfrom(4096)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                continue
            if addr[:2] != self.host:
                continue  # only the hub is heard
            try:
                p = decode(raw, Kind.EVENT)
                if p.type != EventType.STATE:
                    continue
                rep = events.decode_state(p.payload)
            except (PacketError, EventError):
                continue
            self.reports.append(rep)
            del self.reports[:-1024]
            now = time.monotonic()
            for state, fut in self._waiters.get(rep.robot, []):
                if state == rep.state and not fut.done():
                    fut.set_result(now)

    async def _keep(self) -> None:
        while True:
            await asyncio.sleep(KEEPALIVE_S)
            with contextlib.suppress(OSError):
                self._send(EventType.NOP, self.hub, b"")
