"""VDC's four messages as SnP-MrT packets (seed 002), and a link carrying them over UDP sockets.

Each module's cycle is two time-bounded queries, as the slides have it:
- [A, B]: the module's query, inputs its joint position and velocity (A), wanting the 20 values of
  B (qd_r, qdd_r, and its body's V_r, dV_r and V, six each); the master's reply carries them;
- [C, D]: inputs its body's required net force/moment F*_r (C, six values), wanting its joint's
  torque tau_r (D).
A module that computes its [C, D] itself ("local") makes its cycle one query: [A, B] with its last
F*_r beside A (A_LOCAL_QUERY), wanting B and the force the bodies outboard of it need of it, carried
into its body's frame (G, six values: B_LOCAL_REPLY); it computes C and D from them.  One that
takes G from its outboard neighbour ("neighbour") asks the same, then waits for that G of this
cycle (G_PASS, its items the G ids of its joint, its query id the cycle's number), the master's G
being the guess if it does not come, and passes its own on inwards.
Values travel as SnP-MrT items (id, 32-bit float, timestamp): the arithmetic on either side is in
64 bits, the wire rounds to 32.  Item ids are the SnP cycle's (cell.snp.modular.item: its robot,
a quantity, the joint), with quantities of the modular robot's own for B and F*.

`SnpLink` is a `cell.modular.loop.Link`: each message is encoded, sent from its sender's socket to
its receiver's (one per module and one for the master, on loopback), received and decoded there,
and what came out is what the other side uses.  A datagram that does not decode as the wanted
shape, answers another query, belongs to a cycle before or never comes is counted and taken as
lost (the loop then guesses).
"""

from __future__ import annotations

import functools
import itertools
import socket
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from cell.modular.reference import CYCLE_NS
from cell.modular.vdc import A, B, C, D
from cell.snp.modular import TORQUE, item
from cell.snp.packet import Pid, Quantity, query_shape, reply_shape

B_BASE, F_BASE, G_BASE = 16, 48, 56  # the modular robot's own quantities: B's 20 values 16..35,
# F*'s 48..53, the outboard bodies' force carried in 56..61
A_QUERY, B_REPLY = query_shape(2, 20), reply_shape(20)
C_QUERY, D_REPLY = query_shape(6, 1), reply_shape(1)
A_LOCAL_QUERY, B_LOCAL_REPLY = query_shape(8, 26), reply_shape(26)
G_PASS = reply_shape(6)  # "neighbour": a module's force to its inboard neighbour, G of that one's joint


@functools.cache
def ids_of(joint: int) -> tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...], int]:
    """Joint's item ids (the SnP cycle's robot, cell.snp.modular.item): A's, B's, F*'s, and tau_r's."""
    a = (item(Quantity.POSITION, joint), item(Quantity.VELOCITY, joint))
    b = tuple(item(B_BASE + k, joint) for k in range(20))
    f = tuple(item(F_BASE + k, joint) for k in range(6))
    return a, b, f, item(TORQUE, joint)


@functools.cache
def outboard_ids(joint: int) -> tuple[int, ...]:
    """Joint's G item ids: the force its outboard bodies need of its body (a local [C, D]'s)."""
    return tuple(item(G_BASE + k, joint) for k in range(6))


def b_values(b: B) -> list[float]:
    return [b.qd_r, b.qdd_r, *b.v_r, *b.a_r, *b.v]


def b_of(values: tuple | list) -> B:
    v = np.asarray(values, dtype=np.float64)
    return B(float(v[0]), float(v[1]), v[2:8], v[8:14], v[14:20])


@dataclass
class LinkCounters:
    datagrams: int = 0
    bytes: int = 0
    refused: int = 0  # datagrams that did not decode as the message wanted (taken as lost)
    # per cycle: its 24 messages, encode to decode (the last 200,000 cycles: a service runs for days)
    transit_ns: deque[int] = field(default_factory=lambda: deque(maxlen=200_000))


class SnpLink:
    """The four messages over SnP-MrT on loopback UDP sockets (a master's, one per module)."""

    def __init__(self, modules: int = 6, host: str = "127.0.0.1") -> None:
        def sock() -> socket.socket:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind((host, 0))
            s.settimeout(0.05)  # (loopback delivers at once: a wait this long is a loss)
            return s

        self.master = sock()
        self.modules = [sock() for _ in range(modules)]
        self._addr = {s: s.getsockname() for s in (self.master, *self.modules)}
        self.ids = [ids_of(j) for j in range(modules)]
        self.counters = LinkCounters()
        self._qid = 0
        self._asked = [0] * modules  # each module's query in flight
        self._cycle_ns = 0
        self._t = 0  # the cycle's timestamp (ns, cycle count x 1 ms)

    def report(self) -> dict[str, float]:
        """For a service's heartbeat: the packets so far, those refused (and guessed), and the p99 of
        what a cycle's 24 messages took over the last 1,000 cycles."""
        c = self.counters
        recent = list(itertools.islice(reversed(c.transit_ns), 1000)) or [0]
        return {
            "modular.datagrams": c.datagrams,
            "modular.refused": c.refused,
            "modular.exchange_us_p99": float(np.percentile(recent, 99)) / 1e3,
        }

    def close(self) -> None:
        for s in (self.master, *self.modules):
            s.close()

    def _carry(self, src: socket.socket, dst: socket.socket, data: bytes) -> bytes:
        """The datagram as `dst` reads it (b"": none came: taken as lost, like one that fails to decode)."""
        t0 = time.perf_counter_ns()
        src.sendto(data, self._addr[dst])
        try:
            got = dst.recv(2048)
        except TimeoutError:
            got = b""
        self._cycle_ns += time.perf_counter_ns() - t0
        self.counters.datagrams += 1
        self.counters.bytes += len(data)
        return got

    def new_cycle(self) -> None:
        if self._cycle_ns:
            self.counters.transit_ns.append(self._cycle_ns)
        self._cycle_ns = 0
        self._t += CYCLE_NS

    def a(self, i: int, a: A) -> A | None:
        (pos, vel), b_ids, _, _ = self.ids[i]
        self._qid = self._asked[i] = (self._qid + 1) & 0xFFFFFFFF
        t = self._t
        q = A_QUERY.pack(0, Pid.MRT, i + 1, 0, self._qid, t + CYCLE_NS,
                         (pos, a.q, t, vel, a.qd, t), tuple(x for k in b_ids for x in (k, t)))  # fmt: skip
        f = A_QUERY.parse(self._carry(self.modules[i], self.master, q))
        if f is None or f[11] != pos or f[14] != vel or f[13] != t:  # (t: not a late one of a cycle before)
            self.counters.refused += 1
            return None
        return A(f[12], f[15])

    def b(self, i: int, b: B) -> B | None:
        _, b_ids, _, _ = self.ids[i]
        items = tuple(x for k, v in zip(b_ids, b_values(b), strict=True) for x in (k, v, self._t))
        r = B_REPLY.pack(0, Pid.MRT, 0, i + 1, self._asked[i], items)
        f = B_REPLY.parse(self._carry(self.master, self.modules[i], r))
        if f is None or f[8] != self._asked[i] or f[10::3][:20] != b_ids:
            self.counters.refused += 1
            return None
        return b_of(f[11::3][:20])

    def c(self, i: int, c: C) -> C | None:
        _, _, f_ids, tau = self.ids[i]
        self._qid = self._asked[i] = (self._qid + 1) & 0xFFFFFFFF
        t = self._t
        inputs = tuple(x for k, v in zip(f_ids, c.f_star, strict=True) for x in (k, float(v), t))
        q = C_QUERY.pack(0, Pid.MRT, i + 1, 0, self._qid, t + CYCLE_NS, inputs, (tau, t))
        f = C_QUERY.parse(self._carry(self.modules[i], self.master, q))
        if f is None or f[11:29:3] != f_ids or f[13] != t:
            self.counters.refused += 1
            return None
        return C(np.array(f[12:30:3], dtype=np.float64))

    def d(self, i: int, d: D) -> D | None:
        tau = self.ids[i][3]
        r = D_REPLY.pack(0, Pid.MRT, 0, i + 1, self._asked[i], (tau, d.tau_r, self._t))
        f = D_REPLY.parse(self._carry(self.master, self.modules[i], r))
        if f is None or f[8] != self._asked[i] or f[10] != tau:
            self.counters.refused += 1
            return None
        return D(f[11])
