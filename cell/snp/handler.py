"""The SnP handler, sans IO: datagrams in, datagrams out, with the clock passed in.

- SnP-MrT: a time-bounded query is answered before its deadline or denied.
  The decision is made up front from a running estimate of the handler's own
  service time (and made again when the query's turn comes); pending queries
  are served earliest deadline first; a cancellation removes a pending query
  (its asker gets a CANCELLED denial).
- SnP-TSP: a time request is answered with the receive and send times on this
  node's clock (the cell clock, when this node is the master).
- PID management: "do you support PID N?", "list your PIDs".
- Errors: a bad header CRC is dropped (the return path cannot be trusted); a
  bad data CRC, an unknown protocol id or packet type get their error reply.
Every outcome is counted; nothing a peer sends raises out of here.
"""

from __future__ import annotations

import heapq
import itertools
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from cell.counters import Counters, tally
from cell.snp.packet import (
    Cancel,
    Denial,
    Denied,
    ErrorReply,
    Header,
    Item,
    Packet,
    PacketError,
    PacketType,
    Pid,
    PidQuery,
    PidReply,
    Query,
    Refusal,
    Reply,
    TimeRequest,
    TimeResponse,
    decode,
    encode,
)

Address = Any  # whatever the transport uses to answer (a (host, port) pair for UDP)


class StateSource(Protocol):
    """Where the values of items come from."""

    def known(self, item: int) -> bool: ...

    def value(self, item: int, t_ns: int) -> float: ...

    def refine(self, item: Item) -> None: ...


# A pending query, in the heap: [deadline, seq, make, arg, addr, query id, answer header].
# make(arg) returns the reply datagram; seq is set to -1 when the query is cancelled.
# (Lists, not objects: a node that answers a thousand queries a second queues them cheaply.)
_DEADLINE, _SEQ, _MAKE, _ARG, _ADDR, _QID, _BACK = range(7)
Pending = list[Any]


@dataclass(slots=True)
class HandlerCounters(Counters):
    """What a handler did; a refused datagram under its packet.Refusal's name, a denial under
    denied.<why>."""

    packets_in: int = 0
    queries: int = 0
    replies: int = 0
    late: int = 0  # replies sent past their deadline (the service-time estimate was too low)
    cancellations: int = 0
    cancelled: int = 0  # cancellations that took a pending query back
    time_requests: int = 0
    pid_queries: int = 0
    socket_errors: int = 0
    bad_header: int = 0
    bad_header_crc: int = 0
    unknown_pid: int = 0
    malformed: int = 0
    bad_data_crc: int = 0
    unknown_type: int = 0
    denied: dict[str, int] = tally(keys=tuple(d.name.lower() for d in Denial))

    def refused(self, why: Refusal) -> None:
        setattr(self, why.value, getattr(self, why.value) + 1)


class Handler:
    PIDS = (Pid.MRT, Pid.TSP, Pid.PID_MANAGEMENT)

    def __init__(
        self,
        source: StateSource,
        clock: Callable[[], int],
        service_ns: int = 200_000,
        *,
        margin: float = 2.0,
        floor_ns: int = 20_000,
    ) -> None:
        self.source, self.clock = source, clock
        self._pids = frozenset(int(p) for p in self.PIDS)
        self.service_ns = service_ns  # running estimate of the time to serve one query (ns)
        # the estimate is `margin` x the time a reply takes to make, at least floor_ns: 2x on an
        # event loop (the send and the wake-up cost as much again), less in a blocking loop
        self.margin, self.floor_ns = margin, floor_ns
        self._pending: list[Pending] = []
        self._by_id: dict[tuple[Address, int], Pending] = {}
        self._seq = itertools.count()
        self.counters = HandlerCounters()
        self.denials: deque[tuple[int, int, Address]] = deque(maxlen=1000)  # (query id, why, asker)

    # --- input ---------------------------------------------------------------------------------

    def receive(self, datagram: bytes, addr: Address) -> list[tuple[bytes, Address]]:
        """Take one datagram; the datagrams to send at once (queries wait for serve())."""
        t_in = self.clock()
        self.counters.packets_in += 1
        try:
            pkt = decode(datagram, self._pids)
        except PacketError as exc:
            self.counters.refused(exc.counter)
            if exc.reply is None:
                return []
            return [(self._encode(exc.reply), addr)]
        except Exception:  # a bug in decode must not stop the service
            self.counters.malformed += 1
            return []
        return self.dispatch(pkt, addr, t_in)

    def dispatch(self, pkt: Packet, addr: Address, t_in: int) -> list[tuple[bytes, Address]]:
        """A packet decoded already (by a node that takes more types than the handler)."""
        back = pkt.header.reversed()
        body = pkt.body
        pid = pkt.header.pid
        if pid == Pid.MRT and isinstance(body, Query):
            return self._query(body, pkt.header, addr, t_in)
        if pid == Pid.MRT and isinstance(body, Cancel):
            pending = self._by_id.pop((addr, body.query_id), None)
            self.counters.cancellations += 1
            if pending is None:
                return []  # already served or unknown: nothing to take back
            pending[_SEQ] = -1  # marks it cancelled in the heap
            self.counters.cancelled += 1
            self.denials.append((body.query_id, int(Denial.CANCELLED), addr))
            return [(encode(back, Denied(body.query_id, Denial.CANCELLED)), addr)]
        if pid == Pid.TSP and isinstance(body, TimeRequest):
            self.counters.time_requests += 1
            return [(encode(back, TimeResponse(body.t1, t_in, self.clock())), addr)]
        if pid == Pid.PID_MANAGEMENT and isinstance(body, PidQuery):
            self.counters.pid_queries += 1
            if pkt.type == PacketType.PID_LIST_QUERY:
                return [(encode(back, PidReply(tuple(int(p) for p in self.PIDS))), addr)]
            pids = (body.pid,) if body.pid in self.PIDS else ()
            return [(encode(back, PidReply(pids), type=PacketType.PID_SUPPORTED_REPLY), addr)]
        # a valid packet of a type this end does not take (a reply sent to the handler, a time
        # request on the MrT protocol id, ...): answer that it is unknown here
        self.counters.unknown_type += 1
        return [(encode(back, ErrorReply(pkt.type), type=PacketType.UNKNOWN_PACKET_TYPE_REPLY), addr)]

    def _query(self, q: Query, header: Header, addr: Address, t_in: int) -> list[tuple[bytes, Address]]:
        self.counters.queries += 1
        back = header.reversed()
        for item in q.inputs:
            if not self.source.known(item.id):
                return [self._deny(back, q.query_id, Denial.UNKNOWN_INPUT_ITEM, addr)]
        for wanted in q.outputs:
            if not self.source.known(wanted.id):
                return [self._deny(back, q.query_id, Denial.UNKNOWN_OUTPUT_ITEM, addr)]
        if not self.admit(t_in, q.deadline):
            return [self._deny(back, q.query_id, Denial.DEADLINE_CANNOT_BE_MET, addr)]
        for item in q.inputs:
            self.source.refine(item)
        self.enqueue(q.deadline, self._reply, (back, q), addr, q.query_id, back)
        return []

    def admit(self, t_in: int, deadline: int) -> bool:
        """Can a query that came in at t_in be answered by its deadline, after those pending?"""
        return t_in + self.service_ns * (1 + len(self._pending)) <= deadline

    def enqueue(
        self, deadline: int, make: Callable[[Any], bytes], arg: Any, addr: Address, qid: int, back: Header
    ) -> None:
        """Queue an admitted query (its inputs taken already): make(arg) will be its reply.  A
        node with a fast path for its own queries' shapes queues them here too, so that every
        query is served earliest deadline first and denied alike."""
        pending = [deadline, next(self._seq), make, arg, addr, qid, back]
        heapq.heappush(self._pending, pending)
        self._by_id[(addr, qid)] = pending

    def deny(self, back: Header, query_id: int, addr: Address) -> tuple[bytes, Address]:
        """The denial of a query that admit() refused."""
        return self._deny(back, query_id, Denial.DEADLINE_CANNOT_BE_MET, addr)

    def _deny(self, back: Header, query_id: int, why: Denial, addr: Address) -> tuple[bytes, Address]:
        self.counters.count("denied", why.name.lower())
        self.denials.append((query_id, int(why), addr))
        return encode(back, Denied(query_id, why)), addr

    def _reply(self, arg: tuple[Header, Query]) -> bytes:
        back, q = arg
        items = tuple(Item(w.id, self.source.value(w.id, w.timestamp), w.timestamp) for w in q.outputs)
        return encode(back, Reply(q.query_id, items))

    # --- serving ---------------------------------------------------------------------------------

    @property
    def pending(self) -> int:
        return len(self._by_id)

    def serve(self) -> tuple[bytes, Address] | None:
        """Answer the pending query with the earliest deadline (or deny it if it can no longer be
        met); None when nothing is pending."""
        while self._pending:
            p = heapq.heappop(self._pending)
            if p[_SEQ] < 0:
                continue  # cancelled
            addr, qid, deadline = p[_ADDR], p[_QID], p[_DEADLINE]
            self._by_id.pop((addr, qid), None)
            t0 = self.clock()
            if t0 + self.service_ns > deadline:
                return self._deny(p[_BACK], qid, Denial.DEADLINE_CANNOT_BE_MET, addr)
            out = p[_MAKE](p[_ARG])
            t1 = self.clock()
            self.service_ns = max(self.floor_ns, int(0.9 * self.service_ns + 0.1 * (t1 - t0) * self.margin))
            if t1 > deadline:
                self.counters.late += 1  # should not happen: the estimate was too low
            self.counters.replies += 1
            return out, addr
        return None

    def _encode(self, pkt: Packet) -> bytes:
        return encode(pkt.header, pkt.body, type=pkt.type)
