"""A Responsive Link node on UDP sockets: the message handler of the paper's Sec. 3, on asyncio.

Each of a node's links L1-L4 is two UDP sockets, an event link and a data
link, each bound locally and sending to its peer's.  L0 is the host: this
process, which sends with send() and takes what is addressed to it through
the on_event / on_data callbacks.

Events come first everywhere.  Their sockets are read the moment they are
readable, each event is routed and sent on at once, and each one addressed
to the host is handed over by itself (the paper's mailbox); the time from its arrival on a
link to that is kept (event_latency_ns).  Data are
handled in slices of at most `slice_packets` packets, and before each slice
the event sockets are drained, so an event waits behind at most one slice,
never behind a backlog.  Data for the host are handed over in batches (the
paper's DMA threshold).  Everything else is counted in the Node (packets,
bytes, queue depths, drops by reason).

A node may also open a host interface (`host`): a UDP socket through which
other local processes act as its host.  What they send there enters the node
on L0, as the host's own packets do, and every event delivered to L0 is copied
to each of them that spoke in the last HOST_LEASE_S (clients keep their
lease with NOP events).
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass

from cell.rlink.node import Node
from cell.rlink.packet import Kind, Packet, encode

SLICE = 4  # data packets handled between two looks at the event sockets (`cell bench rlink`: at 32 a
# flooded node made events wait 4x longer; at 4 about 1.1x, and it handles as many data packets a second)
HOST_LEASE_S = 5.0  # a host-interface client that has not sent anything for this long hears nothing
# host-interface clients that hear the events at once: each costs a sendto per event, so a peer sending
# from thousands of ports must not make every e-stop wait for thousands of copies (beyond: counted,
# their events still enter the node, they hear nothing back)
MAX_CLIENTS = 64
RECV_BYTES = 4096  # a datagram larger than any line form, so that oversized ones are seen whole


@dataclass(frozen=True)
class LinkPorts:
    """Link `link` (1..4) of a node: where its event and data sockets bind and whom they send to."""

    link: int
    event: tuple[str, int]
    data: tuple[str, int]
    peer_event: tuple[str, int]
    peer_data: tuple[str, int]


class NodeLink:
    def __init__(
        self,
        node: Node,
        links: list[LinkPorts],
        on_event: Callable[[Packet], None] | None = None,
        on_data: Callable[[list[Packet]], None] | None = None,
        slice_packets: int = SLICE,
        host: tuple[str, int] | None = None,
    ) -> None:
        self.node = node
        self.on_event = on_event or (lambda _p: None)
        self.on_data = on_data or (lambda _b: None)
        self.slice = slice_packets
        self.ports = {p.link: p for p in links}
        self.socks: dict[tuple[int, Kind], socket.socket] = {}
        self.event_latency_ns: list[int] = []  # arrival on a link -> handed to the host, recent
        self.host_sock: socket.socket | None = None
        self.clients: dict[tuple[str, int], float] = {}  # host-interface client -> when it last spoke
        self.clients_refused = 0  # events from a client beyond MAX_CLIENTS (served, not answered)
        try:
            if host is not None:
                self.host_sock = _udp(host)
            for p in links:
                for kind, addr in ((Kind.EVENT, p.event), (Kind.DATA, p.data)):
                    self.socks[p.link, kind] = _udp(addr)
        except BaseException:
            self.close()
            raise
        self._data_ready = asyncio.Event()
        self.arrived_ns = 0  # when the events being handled were read (perf_counter ns)

    def address(self, link: int, kind: Kind) -> tuple[str, int]:
        return self.socks[link, kind].getsockname()[:2]

    def close(self) -> None:
        for s in self.socks.values():
            s.close()
        if self.host_sock is not None:
            self.host_sock.close()

    # --- the host's side -----------------------------------------------------------------------

    def send(self, kind: Kind, dst: int, type: int, payload: bytes = b"", priority: int = 0) -> Packet:
        """A packet from this node's host, sent on its way at once."""
        p = self.node.send(kind, dst, type, payload, priority)
        self.arrived_ns = time.perf_counter_ns()  # (its own events reach the host at once)
        self._flush()
        return p

    # --- the loop --------------------------------------------------------------------------------

    async def run(self) -> None:
        """Serve the links until cancelled."""
        loop = asyncio.get_running_loop()
        fds = []
        try:
            if self.host_sock is not None:
                loop.add_reader(self.host_sock.fileno(), self._host_events)
                fds.append(self.host_sock.fileno())
            for (_link, kind), s in self.socks.items():
                if kind == Kind.EVENT:
                    loop.add_reader(s.fileno(), self._events)
                else:
                    loop.add_reader(s.fileno(), self._data_ready.set)
                fds.append(s.fileno())
            while True:
                await self._data_ready.wait()
                self._data_ready.clear()
                while self._data_slice():  # more may wait: another slice, after the loop's turn  # noqa: ASYNC110
                    await asyncio.sleep(0)
        finally:
            for fd in fds:
                with contextlib.suppress(Exception):
                    loop.remove_reader(fd)

    def poll_events(self) -> None:
        """Take the events waiting now, from outside the loop's turn: a host busy with a long piece of
        work (the data plane's batch) calls this between its slices."""
        self._events()

    def _events(self) -> None:
        """Every event waiting on every link: routed, sent on, handed to the host one by one."""
        got = False
        self.arrived_ns = time.perf_counter_ns()
        for (link, kind), s in self.socks.items():
            if kind != Kind.EVENT:
                continue
            while True:
                try:
                    raw = s.recv(RECV_BYTES)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:  # e.g. an ICMP error from a peer that is not up yet
                    continue
                self.node.receive(link, Kind.EVENT, raw)
                got = True
        if got:
            self._flush()

    def _host_events(self) -> None:
        """Events local processes send through the host interface: they enter on L0."""
        assert self.host_sock is not None
        self.arrived_ns = time.perf_counter_ns()
        now = time.monotonic()
        got = False
        while True:
            try:
                raw, addr = self.host_sock.recvfrom(RECV_BYTES)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                continue
            self._lease(addr, now)
            self.node.receive(0, Kind.EVENT, raw)
            got = True
        if got:
            self._flush()

    def _lease(self, addr: tuple[str, int], now: float) -> None:
        clients = self.clients
        if addr not in clients and len(clients) >= MAX_CLIENTS:
            for old, seen in list(clients.items()):  # make room from the expired leases, if any
                if now - seen > HOST_LEASE_S:
                    del clients[old]
        if addr in clients or len(clients) < MAX_CLIENTS:
            clients[addr] = now
        else:
            self.clients_refused += 1

    def _data_slice(self) -> bool:
        """At most one slice of data packets (the events first); True if more may be waiting."""
        self._events()
        n = 0
        for (link, kind), s in self.socks.items():
            if kind != Kind.DATA:
                continue
            while n < self.slice:
                try:
                    raw = s.recv(RECV_BYTES)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    continue
                self.node.receive(link, Kind.DATA, raw)
                n += 1
        self._flush()
        return n >= self.slice

    def _flush(self) -> None:
        """Send what every link has queued, in the node's order (events overtake data)."""
        node = self.node
        batch: list[Packet] = []
        while (out := node.next_out(0)) is not None:  # to this host
            kind, p = out
            if kind == Kind.EVENT:
                self._deliver_event(p)
            else:
                batch.append(p)
        if batch:
            self.on_data(batch)
        for link, ports in self.ports.items():
            while (out := node.next_out(link)) is not None:
                kind, p = out
                sock = self.socks[link, kind]
                try:
                    sock.sendto(
                        node.wire(link, p), ports.peer_event if kind == Kind.EVENT else ports.peer_data
                    )
                except (BlockingIOError, InterruptedError):
                    node.links[link].overflow[kind] += 1  # the socket's buffer is full: counted, dropped
                except OSError:
                    node.links[link].overflow[kind] += 1  # the peer is not there (yet)

    def _deliver_event(self, p: Packet) -> None:
        lat = self.event_latency_ns
        lat.append(time.perf_counter_ns() - self.arrived_ns)
        if len(lat) > 4096:
            del lat[:2048]
        if self.clients:
            self._to_clients(p)
        self.on_event(p)

    def _to_clients(self, p: Packet) -> None:
        assert self.host_sock is not None
        raw, now = encode(p), time.monotonic()
        for addr, seen in list(self.clients.items()):
            if now - seen > HOST_LEASE_S:
                del self.clients[addr]
                continue
            try:
                self.host_sock.sendto(raw, addr)
            except OSError:  # gone, or its buffer is full: it hears this one no more
                self.node.links[0].overflow[Kind.EVENT] += 1


def link_counters(link: NodeLink, prefix: str = "rlink") -> dict[str, float]:
    """A node's counters as flat names: per link and kind, drops by reason, event latency."""
    node = link.node
    out: dict[str, float] = {}
    for n, c in enumerate(node.links):
        if not any(c.packets_in) and not any(c.packets_out):
            continue
        for kind in Kind:
            k = f"{prefix}.L{n}.{kind.name.lower()}"
            out[f"{k}.packets_in"] = c.packets_in[kind]
            out[f"{k}.packets_out"] = c.packets_out[kind]
            out[f"{k}.bytes_in"] = c.bytes_in[kind]
            out[f"{k}.bytes_out"] = c.bytes_out[kind]
            out[f"{k}.overflow"] = c.overflow[kind]
            out[f"{k}.depth"] = node.pending(n, kind)
            out[f"{k}.depth_max"] = c.depth_max[kind]
        if c.fec_corrected:
            out[f"{prefix}.L{n}.fec_corrected"] = c.fec_corrected
    out.update({f"{prefix}.drops.{r}": v for r, v in node.drops.items()})
    if link.host_sock is not None:
        out[f"{prefix}.host_clients"] = len(link.clients)
        out[f"{prefix}.host_clients_refused"] = link.clients_refused
    if link.event_latency_ns:
        ns = sorted(link.event_latency_ns)
        out[f"{prefix}.event_latency_p50_us"] = ns[len(ns) // 2] / 1e3
        out[f"{prefix}.event_latency_p99_us"] = ns[min(len(ns) - 1, int(len(ns) * 0.99))] / 1e3
    return out


def _udp(addr: tuple[str, int]) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        s.bind(addr)
        s.setblocking(False)
    except BaseException:
        s.close()
        raise
    return s
