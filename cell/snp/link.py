"""A node's link of the modular robot on UDP: its socket (kernel receive and transmit stamps), a
lossy link, and the link over the two routers of seed 002 (cell.snp.routed: the routers themselves).

Below the loops (cell.snp.runner), the C cycles (cell.snp.native) and the routers alike.
"""

from __future__ import annotations

import random
import socket
import struct
import time
from collections.abc import Callable
from typing import Any

from cell.snp.packet import crc8, stamp_departure, time_packet
from cell.snp.spacewire import FAILOVER_CYCLES
from cell.timer import realtime_offset

SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
SO_TIMESTAMPING = getattr(socket, "SO_TIMESTAMPING", 37)
# SO_TIMESTAMPING flags (linux/net_tstamp.h): software stamps reported, the packet not looped back
# with its stamp, each stamp numbered, and no receive stamps added to what the socket reads (the
# loops read SO_TIMESTAMPNS's only); each send asks for its transmit stamp on its own (_TX_STAMP),
# so that only the SnP-TSP time packets leave one in the error queue
_TS_TX_SOFTWARE, _TS_SOFTWARE, _TS_OPT_ID = 1 << 1, 1 << 4, 1 << 7
_TS_OPT_TSONLY, _TS_OPT_RX_FILTER = 1 << 11, 1 << 17
_TX_STAMP = [(socket.SOL_SOCKET, SO_TIMESTAMPING, struct.pack("=I", _TS_TX_SOFTWARE))]
_CMSG = socket.CMSG_SPACE(16)
_TIMESPEC = struct.Struct("=qq")


def open_udp(host: str = "127.0.0.1", port: int = 0, *, timestamps: bool = False) -> socket.socket:
    """timestamps: the kernel stamps each datagram as it comes in (drain gives it)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    if timestamps:
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    sock.bind((host, port))
    sock.setblocking(False)
    return sock


def _kernel_tx_stamps(sock: socket.socket) -> bool:
    """Make sock report the kernel's transmit stamps of the sends that ask (False: it cannot)."""
    flags = _TS_SOFTWARE | _TS_OPT_ID | _TS_OPT_TSONLY | _TS_OPT_RX_FILTER
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPING, flags)
    except OSError:  # (no RX filter before Linux 6.12: what it receives would carry a second stamp)
        return False
    return True


class Link:
    """Sends on a socket, dropping `loss` of the datagrams (seeded): a lossy SpaceWire link, and the
    time-stamping port of its node.

    clock: the sender's clock, from the host's (CLOCK_MONOTONIC ns -> the sender's ns).  An SnP-TSP
    time packet gets the time it leaves written in (packet.stamp_departure: one-step stamping),
    read just before the send call.  Where the kernel stamps what the socket sends, the link also
    asks for that stamp and tells `departed(datagram, t)` when the packet really left, and sends
    what it returns (packet.follow_up's: two-step stamping, as PTP's two-step clocks).  clock None:
    sent as dated when made."""

    def __init__(
        self,
        sock: socket.socket,
        loss: float = 0.0,
        seed: int = 0,
        clock: Callable[[int], int] | None = None,
        departed: Callable[[bytes, int], list[bytes]] | None = None,
    ) -> None:
        self.sock, self.loss, self.rng = sock, loss, random.Random(seed)
        self.clock, self.departed = clock, departed
        self.sent = self.lost = self.errors = 0
        self.two_step = clock is not None and departed is not None and _kernel_tx_stamps(sock)
        self.unstamped = 0  # two-step sends whose stamp the kernel did not give at once
        self.mono_of_real = realtime_offset()

    def send(self, data: bytes, addr: Any) -> None:
        if addr is None:
            return
        if self.loss and self.rng.random() < self.loss:
            self.lost += 1
            return
        clock = self.clock if self.clock is not None and time_packet(data) is not None else None  # (timed)
        if clock is not None:
            data = stamp_departure(data, clock(time.monotonic_ns()))
        two_step = clock is not None and self.two_step
        wire, to = self._wire(data, addr)
        try:
            if two_step:
                self.sock.sendmsg([wire], _TX_STAMP, 0, to)
            else:
                self.sock.sendto(wire, to)
            self.sent += 1
        except OSError:  # a full buffer, or the peer's port gone (ICMP): the link loses it
            self.errors += 1
            return
        if two_step:
            t = self._tx_stamp()
            if t is None:
                self.unstamped += 1
                return
            assert clock is not None and self.departed is not None  # (two_step: both given)
            for more in self.departed(data, clock(t)):
                self.send(more, addr)

    def _wire(self, data: bytes, addr: Any) -> tuple[bytes, Any]:
        """What goes on the wire for data to addr, and where (a routed link: cell.snp.routed)."""
        return data, addr

    def received(self, data: bytes, addr: Any) -> tuple[bytes, Any] | None:
        """A datagram off the wire as its node takes it: (packet, sender); None: dropped."""
        return data, addr

    def _tx_stamp(self) -> int | None:
        """The kernel's transmit stamp of the last send (CLOCK_MONOTONIC ns), from the error queue
        (emptied: a stamp left there would keep a polling loop awake); None if none is there.  On
        loopback the stamp is queued within the send call; a NIC may give it later (then lost)."""
        t = None
        while True:
            try:
                _data, anc, _flags, _addr = self.sock.recvmsg(0, 256, socket.MSG_ERRQUEUE)
            except OSError:  # (BlockingIOError: no more)
                return t
            for level, kind, raw in anc:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPING and len(raw) >= 16:
                    sec, nsec = _TIMESPEC.unpack_from(raw)
                    t = sec * 1_000_000_000 + nsec - self.mono_of_real


def drain(sock: socket.socket, mono_of_real: int = 0, limit: int = 256) -> list[tuple[bytes, Any, int]]:
    """(data, sender, arrival on CLOCK_MONOTONIC) for each datagram waiting: on a socket opened
    with timestamps, the kernel's stamp (CLOCK_REALTIME) less mono_of_real, so that a busy loop
    does not date what it reads late; else when it was read."""
    out = []
    for _ in range(limit):
        try:
            data, anc, _flags, addr = sock.recvmsg(2048, _CMSG)
        except BlockingIOError:
            break
        except OSError:
            continue
        at = time.monotonic_ns()
        for level, kind, raw in anc:
            if kind == SO_TIMESTAMPNS and level == socket.SOL_SOCKET and len(raw) >= 16:
                sec, nsec = _TIMESPEC.unpack_from(raw)
                at = sec * 1_000_000_000 + nsec - mono_of_real
        out.append((data, addr, at))
    return out


MASTER_PORT = 1  # on both routers: the master's link; module k's is port 2 + k
ROUTERS = 2
FAILOVER_SENDS = 2 * FAILOVER_CYCLES  # a module's sends with nothing heard (two queries a cycle)


def module_port(k: int) -> int:
    return 2 + k


def with_return(data: bytes, ret: bytes) -> bytes:
    """The packet with `ret` as its return address (it had none), its header CRC made anew."""
    if len(data) < 12 or data[2]:
        return data
    head = data[:2] + bytes([len(ret)]) + ret + data[3:11]
    return head + bytes([crc8(head)]) + data[12:]


def without_return(data: bytes) -> tuple[bytes, tuple[int, ...]] | None:
    """(the packet with no return address, its header CRC made anew; the return address), or None
    for a datagram whose header does not hold together (dropped by the caller, counted)."""
    if len(data) < 12:
        return None
    n = data[2]
    end = 3 + n + 8
    if len(data) < end + 2 or crc8(data[:end]) != data[end]:
        return None
    head = data[:2] + b"\x00" + data[3 + n : end]
    return head + bytes([crc8(head)]) + data[end + 1 :], tuple(data[3 : 3 + n])


class RoutedLink(Link):
    """A node's link over the two routers (see the module docstring).  `links`: the router ports
    this node's socket is joined to, R1's then R2's; `own`: its return address; `failover_after`:
    sends in a row with nothing heard before it moves to the other router (None: it answers each
    peer through the router it last heard that peer on, as the master does)."""

    def __init__(
        self,
        sock: socket.socket,
        links: tuple[Any, Any],
        own: tuple[int, ...],
        *,
        failover_after: int | None = None,
        **kw: Any,
    ) -> None:
        super().__init__(sock, **kw)
        self.links, self.own, self.failover_after = links, bytes(own), failover_after
        self.active = 0  # the router it sends through (a module's)
        self.via: dict[tuple[int, ...], Any] = {}  # a peer's router, as last heard (the master's)
        self.unheard = 0  # sends since it last heard anything
        self.failovers = 0
        self.refused = 0  # datagrams from outside its links, or whose header does not hold

    def received(self, data: bytes, addr: Any) -> tuple[bytes, Any] | None:
        if addr not in self.links:
            self.refused += 1
            return None
        got = without_return(data)
        if got is None or not got[1]:
            self.refused += 1
            return None
        packet, ret = got
        self.via[ret] = addr
        self.unheard = 0
        return packet, ret

    def _wire(self, data: bytes, addr: Any) -> tuple[bytes, Any]:
        if self.failover_after is not None:
            self.unheard += 1
            if self.unheard > self.failover_after:
                self.active, self.unheard = 1 - self.active, 0
                self.failovers += 1
            router = self.links[self.active]
        else:
            router = self.via.get(addr, self.links[0])
        return bytes(addr) + with_return(data, self.own), router
