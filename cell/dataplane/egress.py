"""An egress port with a line rate, a buffer and a scheduler: one shared FIFO or strict priority.

The paper's switch forwards ordinary traffic beside the robots' (Sec. 7.1) and,
in Appendix C (Fig. 14), shows what a congested egress port does to robot
commands: in one shared FIFO they wait behind the backlog (3 ms at 5 Gbps) and
are lost when the buffer is full; in a queue of their own served first
(strict priority, as most switches can) they keep sub-millisecond response
times with no loss.

This is that port for a software data plane.  Packets are queued in runs of
equal-sized UDP datagrams (as they arrive with GRO and leave with GSO); the
wire is modelled in virtual time: a packet starts when the wire is free and it
has arrived, takes wire_bytes * 8 / rate to send, and is handed to the kernel
when it has finished (a wake-up that comes late sends what finished meanwhile at
once; the virtual times, and so the rate, stay exact).  Strict priority is non-preemptive: a robot packet
that arrives while an ordinary one is on the wire goes next.  Tail drop per
queue, counted.  Sans-IO apart from the `send` callable each run carries.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

ROBOT, BULK = 0, 1  # traffic classes: robot control first under strict priority
CLASSES = ("robot", "bulk")
OVERHEAD = 8 + 20 + 14 + 4  # UDP, IPv4, Ethernet header and FCS: a datagram's bytes on the wire

Send = Callable[[memoryview, int, tuple], int]  # (datagrams, segment size, address) -> how many went


@dataclass
class Run:
    """Datagrams of one size from one class to one address, queued together."""

    arrival_ns: int
    cls: int
    data: bytes
    seg: int
    addr: tuple
    send: Send
    sent: int = 0  # datagrams of it already on their way

    @property
    def count(self) -> int:
        return len(self.data) // self.seg

    @property
    def left(self) -> int:
        return self.count - self.sent


@dataclass
class ClassCounters:
    enqueued: int = 0
    dropped: int = 0
    sent: int = 0
    delay_ns_max: int = 0  # the longest a packet of this class waited (arrival to wire start)
    delays_ns: list[int] = field(default_factory=list)  # queueing delay of each run's first packet


class EgressPort:
    """A port of `rate_bps` with `buffer_bytes` per queue, `fifo` (one queue for both classes,
    buffer shared) or `priority` (a queue per class, robot first)."""

    def __init__(self, rate_bps: float, buffer_bytes: int, scheduling: Literal["fifo", "priority"]) -> None:
        if rate_bps <= 0 or buffer_bytes <= 0:
            raise ValueError("an egress port needs a rate and a buffer > 0")
        self.ns_per_byte = 8e9 / rate_bps
        self.buffer_bytes = buffer_bytes
        self.scheduling = scheduling
        n = 1 if scheduling == "fifo" else len(CLASSES)
        self.queues: list[deque[Run]] = [deque() for _ in range(n)]
        self.queued_bytes = [0] * n
        self.wire_free_ns = 0  # when the packet on the wire has gone
        self.counters = [ClassCounters() for _ in CLASSES]
        self.bytes_sent = 0

    def _queue(self, cls: int) -> int:
        return 0 if self.scheduling == "fifo" else cls

    def backlog(self) -> int:
        return sum(self.queued_bytes)

    def enqueue(self, cls: int, data: bytes, seg: int, addr: tuple, send: Send, now_ns: int) -> int:
        """Queue data's datagrams (segment size seg) for addr; those that do not fit are dropped.
        Returns how many were taken.  Sends what is due at once."""
        q = self._queue(cls)
        count, wire = len(data) // seg, seg + OVERHEAD
        fit = min(count, max(0, self.buffer_bytes - self.queued_bytes[q]) // wire)
        c = self.counters[cls]
        c.enqueued += fit
        c.dropped += count - fit
        if fit:
            self.queues[q].append(Run(now_ns, cls, data[: fit * seg], seg, addr, send))
            self.queued_bytes[q] += fit * wire
            self.transmit(now_ns)
        return fit

    def _next(self) -> tuple[int, int] | None:
        """(queue, wire start time) of the packet to go next, or None when all are empty."""
        heads = [(i, q[0]) for i, q in enumerate(self.queues) if q]
        if not heads:
            return None
        start = max(self.wire_free_ns, min(r.arrival_ns for _, r in heads))
        for i, r in heads:  # strict priority among the packets there by then (queue 0 first)
            if r.arrival_ns <= start:
                return i, start
        raise AssertionError("unreachable: the earliest head is there by its own arrival")

    def transmit(self, now_ns: int) -> int | None:
        """Hand to the kernel every packet whose wire time has passed; ns until the next, or None."""
        while (nxt := self._next()) is not None:
            qi, start = nxt
            queue = self.queues[qi]
            run = queue[0]
            wire_ns = (run.seg + OVERHEAD) * self.ns_per_byte
            if start + wire_ns > now_ns:
                return int(start + wire_ns - now_ns)
            # as many of the run as have finished by now, and not past a more urgent packet's arrival
            k = min(run.left, int((now_ns - start) // wire_ns))
            for j in range(qi):
                if self.queues[j]:
                    k = min(k, max(1, int(-(-(self.queues[j][0].arrival_ns - start) // wire_ns))))
            c = self.counters[run.cls]
            delay = int(start - run.arrival_ns)
            if run.sent == 0:
                c.delays_ns.append(delay)
                if len(c.delays_ns) > 65536:
                    del c.delays_ns[:32768]
            c.delay_ns_max = max(c.delay_ns_max, delay)
            view = memoryview(run.data)[run.sent * run.seg : (run.sent + k) * run.seg]
            c.sent += run.send(view, run.seg, run.addr)
            run.sent += k
            self.queued_bytes[qi] -= k * (run.seg + OVERHEAD)
            self.bytes_sent += k * (run.seg + OVERHEAD)
            self.wire_free_ns = int(start + k * wire_ns)
            if run.left == 0:
                queue.popleft()
        return None

    def summary(self) -> dict[str, float]:
        out: dict[str, float] = {"backlog_bytes": self.backlog(), "bytes_sent": self.bytes_sent}
        for name, c in zip(CLASSES, self.counters, strict=True):
            out[f"{name}_enqueued"] = c.enqueued
            out[f"{name}_dropped"] = c.dropped
            out[f"{name}_sent"] = c.sent
            out[f"{name}_delay_ms_max"] = c.delay_ns_max / 1e6
        return out
