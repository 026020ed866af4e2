"""A Responsive Link node, sans IO: packets in on its links, routed, queued and overtaken, out again.

Five links: L0 is the node's host (the local process), L1-L4 go point to
point to other nodes, each with an event link and a data link of its own.
`receive()` takes a packet's bytes from a link and `send()` one from the
host; `next_out()` says what a link sends next.  Every output link has a
bounded queue per kind and priority, and the order out is the paper's
overtaking rule: any event before any data, and within a kind the higher
priority first (first come first served within one).  A full queue makes
room by dropping the newest packet of a lower priority, else drops the new
one; either way it is counted, never silent.  Nothing a peer sends can raise
out of here: every bad packet is a drop by reason.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace

from cell.rlink import fec
from cell.rlink.packet import PRIORITIES, SIZE, Drop, Kind, Packet, PacketError, decode, encode
from cell.rlink.routing import LINKS, RoutingTable

DEPTH = 64  # packets queued per output link and kind


@dataclass
class LinkCounters:
    packets_in: list[int] = field(default_factory=lambda: [0, 0])  # per kind
    bytes_in: list[int] = field(default_factory=lambda: [0, 0])
    packets_out: list[int] = field(default_factory=lambda: [0, 0])
    bytes_out: list[int] = field(default_factory=lambda: [0, 0])
    overflow: list[int] = field(default_factory=lambda: [0, 0])  # dropped for a full queue
    depth_max: list[int] = field(default_factory=lambda: [0, 0])
    fec_corrected: int = 0  # bit errors corrected on the way in


class Node:
    def __init__(
        self, address: int, table: RoutingTable, depth: int = DEPTH, fec_links: frozenset[int] = frozenset()
    ) -> None:
        if not 0 <= address <= 255:
            raise ValueError(f"a node address is 0..255 (got {address})")
        self.address = address
        self.table = table
        self.depth = depth
        self.fec_links = fec_links  # links whose line carries FEC-protected bytes
        # queues[link][kind][priority]
        self.queues: list[list[list[deque[Packet]]]] = [
            [[deque() for _ in range(PRIORITIES)] for _ in Kind] for _ in range(LINKS)
        ]
        self.queued = [[0, 0] for _ in range(LINKS)]
        self.links = [LinkCounters() for _ in range(LINKS)]
        self.drops: dict[Drop, int] = dict.fromkeys(Drop, 0)
        self._seq = [0, 0]

    # --- in ------------------------------------------------------------------------------------

    def receive(self, link: int, kind: Kind, raw: bytes) -> None:
        """A packet's bytes as they came on `link`'s event or data link."""
        c = self.links[link]
        c.packets_in[kind] += 1
        c.bytes_in[kind] += len(raw)
        try:
            if link in self.fec_links:
                raw, fixed = _recover(raw, kind)
                c.fec_corrected += fixed
            packet = decode(raw, kind)
        except PacketError as exc:
            self.drops[exc.reason] += 1
            return
        if packet.hops == 0:
            self.drops[Drop.HOPS] += 1
            return
        self._route(packet, came_on=link)

    def send(self, kind: Kind, dst: int, type: int, payload: bytes = b"", priority: int = 0) -> Packet:
        """A packet from this node's host (L0), numbered per kind; routed like any other."""
        seq = self._seq[kind]
        self._seq[kind] = (seq + 1) & 0xFF
        packet = Packet(kind, dst, self.address, priority, type, seq, payload)
        c = self.links[0]
        c.packets_in[kind] += 1
        c.bytes_in[kind] += SIZE[kind]
        self._route(packet, came_on=0)
        return packet

    def _route(self, p: Packet, came_on: int) -> None:
        bitmap, priority = self.table.lookup(p.kind, p.src, p.dst, p.priority)
        bitmap &= ~(1 << came_on) if came_on else ~0  # never back where it came from (the host may loop)
        if not bitmap:
            self.drops[Drop.NO_ROUTE] += 1
            return
        out = replace(p, priority=priority) if priority != p.priority else p
        for link in range(LINKS):
            if bitmap >> link & 1:
                self._enqueue(link, out if link == 0 else replace(out, hops=out.hops - 1))

    def _enqueue(self, link: int, p: Packet) -> None:
        kind, c = p.kind, self.links[link]
        queues = self.queues[link][kind]
        if self.queued[link][kind] >= self.depth:
            lower = next((q for q in queues[: p.priority] if q), None)  # the least urgent first
            if lower is None:
                c.overflow[kind] += 1
                return
            lower.pop()  # the newest of a lower priority makes room
            c.overflow[kind] += 1
            self.queued[link][kind] -= 1
        queues[p.priority].append(p)
        self.queued[link][kind] += 1
        c.depth_max[kind] = max(c.depth_max[kind], self.queued[link][kind])

    # --- out -----------------------------------------------------------------------------------

    def next_out(self, link: int) -> tuple[Kind, Packet] | None:
        """The packet `link` sends next: events overtake data, higher priorities lower ones."""
        for kind in (Kind.EVENT, Kind.DATA):
            if self.queued[link][kind]:
                for q in reversed(self.queues[link][kind]):
                    if q:
                        self.queued[link][kind] -= 1
                        p = q.popleft()
                        c = self.links[link]
                        c.packets_out[kind] += 1
                        c.bytes_out[kind] += SIZE[kind]
                        return kind, p
        return None

    def wire(self, link: int, p: Packet) -> bytes:
        """The bytes for `p` on `link`'s line (FEC-protected where that link is lossy)."""
        raw = encode(p)
        return fec.protect(raw) if link in self.fec_links else raw

    def pending(self, link: int, kind: Kind | None = None) -> int:
        q = self.queued[link]
        return q[0] + q[1] if kind is None else q[kind]


def _recover(line: bytes, kind: Kind) -> tuple[bytes, int]:
    if len(line) != 2 * SIZE[kind]:
        reason = Drop.TRUNCATED if len(line) < 2 * SIZE[kind] else Drop.OVERSIZED
        raise PacketError(reason, f"{len(line)} bytes on an FEC line: {2 * SIZE[kind]} expected")
    try:
        return fec.recover(line)
    except fec.Uncorrectable as exc:
        raise PacketError(Drop.FEC, str(exc)) from None
