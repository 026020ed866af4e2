"""SnP client: time-bounded queries, cancellation, time sync and PID questions over UDP.

    async with SnpClient(("127.0.0.1", 50010)) as snp:
        await snp.sync_time()                        # the cell clock (the master's), filtered
        got = await snp.query(outputs=[(item_id(1, Quantity.POSITION, 0), snp.now() + 5_000_000)],
                              deadline=snp.now() + 2_000_000)
    # -> {item id: Item}, or Denied(explanation), or DeadlineMissed when no answer came in time

On a miss the caller uses a guessed value instead of retrying (failure
handling by data obsolescence): the answer would be obsolete anyway.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import socket
import struct
import sys
import time
from collections.abc import Sequence

from cell.snp.packet import (
    Body,
    Cancel,
    Denial,
    Denied,
    Header,
    Item,
    Packet,
    PacketError,
    PacketType,
    Pid,
    PidQuery,
    PidReply,
    Query,
    Reply,
    TimeRequest,
    TimeResponse,
    Wanted,
    decode,
    encode,
)


class QueryDenied(Exception):
    def __init__(self, query_id: int, explanation: int) -> None:
        self.query_id, self.explanation = query_id, explanation
        try:
            name = Denial(explanation).name
        except ValueError:
            name = str(explanation)
        super().__init__(f"query {query_id} denied: {name}")


class DeadlineMissed(TimeoutError):
    """Neither a reply nor a denial came before the deadline."""


_TIMESTAMP = struct.Struct("qq")  # SO_TIMESTAMPNS's struct timespec (CLOCK_REALTIME)
# (Linux's asm-generic value: Python's socket module does not name it; elsewhere, no stamps)
SO_TIMESTAMPNS = 35 if sys.platform.startswith("linux") else 0
ARRIVAL_GRACE_NS = 500_000  # a reply arriving this long after its query's deadline is still in time


class SnpClient:
    def __init__(self, addr: tuple[str, int], source_process: int = 1, destination_process: int = 0) -> None:
        self.addr = addr
        self.header = Header(0, Pid.MRT, b"", source_process, destination_process)
        self.offset_ns = 0  # cell clock = CLOCK_REALTIME here + offset
        self.delay_ns = 0  # the round trip of the best time exchange
        self._sock: socket.socket | None = None
        self._ids = itertools.count(1)
        self._waiting: dict[tuple[str, int], asyncio.Future[Packet]] = {}
        # when each awaited packet reached this host (the kernel's stamp, CLOCK_REALTIME ns): whether
        # an answer came in time is the wire's to say, not when this process got the CPU to read it
        self._arrived: dict[tuple[str, int], int] = {}
        self.malformed = 0

    async def open(self) -> SnpClient:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setblocking(False)
            if SO_TIMESTAMPNS:  # (no stamps: the time each is read instead)
                sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            sock.connect(self.addr)
            asyncio.get_running_loop().add_reader(sock.fileno(), self._readable)
        except BaseException:
            sock.close()
            raise
        self._sock = sock
        return self

    def close(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(RuntimeError):  # (its loop closed already)
                asyncio.get_running_loop().remove_reader(self._sock.fileno())
            self._sock.close()
            self._sock = None
        for fut in self._waiting.values():
            if not fut.done():
                fut.cancel()

    async def __aenter__(self) -> SnpClient:
        return await self.open()

    async def __aexit__(self, *exc: object) -> None:
        self.close()

    def now(self) -> int:
        """The cell clock, ns."""
        return time.time_ns() + self.offset_ns

    # --- plumbing ----------------------------------------------------------------------------------

    def _readable(self) -> None:
        """Every datagram waiting, with the time it arrived."""
        assert self._sock is not None
        while True:
            try:
                data, anc, _, _ = self._sock.recvmsg(65536, socket.CMSG_SPACE(_TIMESTAMP.size))
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # (an ICMP error of an earlier send: the handler is not there yet)
                continue
            arrived = time.time_ns()
            for level, kind, raw in anc:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(raw) >= 16:
                    sec, nsec = _TIMESTAMP.unpack_from(raw)
                    arrived = sec * 1_000_000_000 + nsec
            self._received(data, arrived)

    def _received(self, data: bytes, arrived_ns: int) -> None:
        try:
            pkt = decode(data)
        except PacketError:
            self.malformed += 1
            return
        body = pkt.body
        if isinstance(body, Reply | Denied):
            key = ("q", body.query_id)
        elif isinstance(body, TimeResponse):
            key = ("t", body.t1)
        elif isinstance(body, PidReply):
            key = ("p", 0)
        else:
            key = ("e", 0)  # an error reply: whoever waits for one
        fut = self._waiting.pop(key, None)
        if fut is not None and not fut.done():
            self._arrived[key] = arrived_ns
            fut.set_result(pkt)

    def _send(self, pid: int, body: Body, type: int | None = None) -> None:
        if self._sock is None:
            raise RuntimeError("the SnP client is not open")
        h = Header(
            self.header.destination, pid, b"", self.header.source_process, self.header.destination_process
        )
        self.send_raw(encode(h, body, type=type))

    def send_raw(self, datagram: bytes) -> None:
        """One datagram to the handler as it is (tests: malformed ones)."""
        if self._sock is None:
            raise RuntimeError("the SnP client is not open")
        with contextlib.suppress(BlockingIOError, ConnectionRefusedError):  # (lost, as UDP may)
            self._sock.send(datagram)

    def _expect(self, key: tuple[str, int]) -> asyncio.Future[Packet]:
        fut: asyncio.Future[Packet] = asyncio.get_running_loop().create_future()
        self._waiting[key] = fut
        return fut

    # --- the API -----------------------------------------------------------------------------------

    async def query(
        self,
        outputs: Sequence[tuple[int, int] | Wanted],
        inputs: Sequence[Item] = (),
        deadline: int | None = None,
        query_id: int | None = None,
    ) -> dict[int, Item]:
        """Values of the output items (id, wanted at ns) before `deadline` (cell clock ns; default
        now + 10 ms): {id: Item}.  QueryDenied, or DeadlineMissed if nothing came in time."""
        qid = next(self._ids) if query_id is None else query_id
        wanted = tuple(w if isinstance(w, Wanted) else Wanted(*w) for w in outputs)
        deadline = self.now() + 10_000_000 if deadline is None else deadline
        fut = self._expect(("q", qid))
        self._send(Pid.MRT, Query(qid, deadline, tuple(inputs), wanted))
        key = ("q", qid)
        try:
            async with asyncio.timeout((deadline - self.now() + ARRIVAL_GRACE_NS) / 1e9):
                pkt = await asyncio.shield(fut)  # (a timeout must not cancel it: read below)
        except TimeoutError:
            self._readable()  # (this process woke late: an answer may be waiting, its arrival says when)
            if not fut.done():
                self._waiting.pop(key, None)
                fut.cancel()
                raise DeadlineMissed(f"query {qid}: no answer before its deadline") from None
            pkt = fut.result()
        except asyncio.CancelledError:
            self._waiting.pop(key, None)
            fut.cancel()
            raise
        late_ns = self._arrived.pop(key, 0) + self.offset_ns - deadline
        if late_ns > ARRIVAL_GRACE_NS:
            raise DeadlineMissed(f"query {qid}: the answer arrived {late_ns / 1e3:.0f} us after its deadline")
        if isinstance(pkt.body, Denied):
            raise QueryDenied(qid, pkt.body.explanation)
        assert isinstance(pkt.body, Reply)
        return {item.id: item for item in pkt.body.items}

    def cancel(self, query_id: int) -> None:
        """Take back a pending query (its answer, a CANCELLED denial, goes to its waiter)."""
        self._send(Pid.MRT, Cancel(query_id))

    async def sync_time(self, rounds: int = 16, timeout: float = 0.2) -> tuple[int, int]:
        """SnP-TSP: align to the cell clock; (offset, round trip) of the exchange with the shortest
        round trip (the least disturbed by queuing), ns."""
        best: tuple[int, int] | None = None
        for _ in range(rounds):
            t1 = time.time_ns()
            fut = self._expect(("t", t1))
            self._send(Pid.TSP, TimeRequest(t1))
            try:
                async with asyncio.timeout(timeout):
                    pkt = await fut
            except TimeoutError:
                self._waiting.pop(("t", t1), None)
                continue
            t4 = self._arrived.pop(("t", t1), time.time_ns())  # (when it arrived, not when read)
            r = pkt.body
            assert isinstance(r, TimeResponse)
            offset = ((r.t2 - r.t1) + (r.t3 - t4)) // 2
            delay = (t4 - r.t1) - (r.t3 - r.t2)
            if best is None or delay < best[1]:
                best = (offset, delay)
        if best is None:
            raise TimeoutError("no time response from the SnP handler")
        self.offset_ns, self.delay_ns = best
        return best

    async def pids(self, timeout: float = 1.0) -> tuple[int, ...]:
        fut = self._expect(("p", 0))
        self._send(Pid.PID_MANAGEMENT, PidQuery(0))
        async with asyncio.timeout(timeout):
            pkt = await fut
        assert isinstance(pkt.body, PidReply)
        return pkt.body.pids

    async def supports(self, pid: int, timeout: float = 1.0) -> bool:
        fut = self._expect(("p", 0))
        self._send(Pid.PID_MANAGEMENT, PidQuery(pid), type=PacketType.PID_SUPPORTED_QUERY)
        async with asyncio.timeout(timeout):
            pkt = await fut
        assert isinstance(pkt.body, PidReply)
        return pid in pkt.body.pids
