"""The modular robot on UDP: blocking epoll loops around the sans-IO master and modules.

No asyncio here: a 1 kHz cycle of two query round trips per module has no room for an event
loop's overhead (an asyncio echo costs 50-75 us on this machine, a blocking socket a few).
Each loop sleeps on epoll with a timerfd armed for the next thing due (Python's epoll waits
in whole milliseconds), drains every readable socket, and sends what the state machines
return.  Several modules run as one process, each with its own socket, address and clock:
the protocol stays on the wire.  `loss` drops that share of sent datagrams (a lossy link).
"""

from __future__ import annotations

import contextlib
import random
import select
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from cell.snp.modular import JointModule, Master
from cell.snp.tsp import Oscillator
from cell.timer import Alarm

COARSE_S = 0.05  # epoll's own timeout: the alarm is what wakes a loop on time


SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_CMSG = socket.CMSG_SPACE(16)


def open_udp(host: str = "127.0.0.1", port: int = 0, *, timestamps: bool = False) -> socket.socket:
    """timestamps: the kernel stamps each datagram as it comes in (drain gives it)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    if timestamps:
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    sock.bind((host, port))
    sock.setblocking(False)
    return sock


class Link:
    """Sends on a socket, dropping `loss` of the datagrams (seeded): a lossy SpaceWire link."""

    def __init__(self, sock: socket.socket, loss: float = 0.0, seed: int = 0) -> None:
        self.sock, self.loss, self.rng = sock, loss, random.Random(seed)
        self.sent = self.lost = self.errors = 0

    def send(self, data: bytes, addr: Any) -> None:
        if addr is None:
            return
        if self.loss and self.rng.random() < self.loss:
            self.lost += 1
            return
        try:
            self.sock.sendto(data, addr)
            self.sent += 1
        except OSError:  # a full buffer, or the peer's port gone (ICMP): the link loses it
            self.errors += 1


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
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(raw) >= 16:
                sec, nsec = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
                at = sec * 1_000_000_000 + nsec - mono_of_real
        out.append((data, addr, at))
    return out


def serve_master(master: Master, sock: socket.socket, stop: Callable[[], bool], loss: float = 0.0) -> Link:
    """Run the master until stop() is true; returns its link (counters)."""
    link = Link(sock, loss, seed=1)
    alarm = Alarm()
    ep = select.epoll()
    ep.register(sock.fileno(), select.EPOLLIN)
    ep.register(alarm.fd, select.EPOLLIN)
    try:
        while not stop():
            alarm.set(master.next_due())
            for fd, _ in ep.poll(COARSE_S):
                if fd == alarm.fd:
                    alarm.clear()
            out: list[tuple[bytes, Any]] = []
            for data, addr, _ in drain(sock):
                out += master.receive(data, addr)
            out += master.serve()
            for data, addr in out:
                link.send(data, addr)
            for data, addr in master.poll():  # after the replies: a beacon leaves as it is dated
                link.send(data, addr)
    finally:
        ep.close()
        alarm.close()
    return link


@dataclass
class Slot:
    """A module on a port of the robot: when it is plugged in and pulled out (s from the start)."""

    module_id: int
    plugged_to: int
    port: int  # UDP port on 127.0.0.1
    plug_s: float = 0.0
    unplug_s: float | None = None
    offset_ns: int = 0  # its oscillator against the master's clock
    drift_ppm: float = 0.0
    transport: str = "snp"
    module: JointModule | None = None
    osc: Oscillator | None = None
    sock: socket.socket | None = None
    link: Link | None = None
    master: Any = None  # the master's address, learnt from its first datagram
    clock_errors: list[int] = field(default_factory=list)  # servoed clock - master's, ns
    plugged_at: int = 0
    next_sample: int = 0


def run_modules(
    slots: list[Slot],
    seconds: float,
    loss: float = 0.0,
    *,
    rmap_timeout_ns: int = 200_000,
    rmap_retries: int = 1,
    sample_ns: int = 10_000_000,
) -> list[Slot]:
    """Run the slots' modules in this thread for `seconds`, plugging and pulling them on time."""
    alarm = Alarm()
    ep = select.epoll()
    ep.register(alarm.fd, select.EPOLLIN)
    by_fd: dict[int, Slot] = {}
    t0 = time.monotonic_ns()
    mono_of_real = time.time_ns() - t0  # (CLOCK_REALTIME - CLOCK_MONOTONIC, for kernel stamps)
    end = t0 + int(seconds * 1e9)

    def plug(s: Slot, now: int) -> None:
        s.osc = Oscillator(s.offset_ns, s.drift_ppm, t0)
        s.module = JointModule(s.module_id, s.plugged_to, port=1)  # (its parent's downstream port)
        s.module.use_transport(s.transport, rmap_timeout_ns, rmap_retries)
        s.sock = open_udp("127.0.0.1", s.port, timestamps=True)
        s.link = Link(s.sock, loss, seed=s.module_id)
        s.plugged_at = now
        by_fd[s.sock.fileno()] = s
        ep.register(s.sock.fileno(), select.EPOLLIN)

    def unplug(s: Slot) -> None:
        assert s.sock is not None
        ep.unregister(s.sock.fileno())
        del by_fd[s.sock.fileno()]
        s.sock.close()
        s.sock = None

    try:
        while True:
            now = time.monotonic_ns()
            if now >= end:
                break
            for s in slots:
                if s.sock is None and s.module is None and now >= t0 + s.plug_s * 1e9:
                    plug(s, now)
                elif s.sock is not None and s.unplug_s is not None and now >= t0 + s.unplug_s * 1e9:
                    unplug(s)
            for fd, _ in ep.poll(COARSE_S):
                if fd == alarm.fd:
                    alarm.clear()
                    continue
                s = by_fd.get(fd)
                if s is None or s.sock is None:
                    continue
                for data, addr, at in drain(s.sock, mono_of_real):
                    s.master = addr
                    assert s.module is not None and s.osc is not None and s.link is not None
                    for out in s.module.receive(data, s.osc.raw(at)):
                        s.link.send(out, addr)
            wake = end
            now = time.monotonic_ns()
            for s in slots:
                if s.sock is None or s.module is None or s.osc is None or s.link is None:
                    if s.module is None:
                        wake = min(wake, t0 + int(s.plug_s * 1e9))
                    continue
                m = s.module
                for out in m.poll(s.osc.raw(now)):
                    s.link.send(out, s.master)
                if m.state == "running" and now >= s.next_sample:
                    s.next_sample = now + sample_ns
                    s.clock_errors.append(m.servo.now(s.osc.raw(now)) - now)
                w = m.next_wake()
                if w is not None:
                    wake = min(wake, s.osc.true(w))
                if s.unplug_s is not None:
                    wake = min(wake, t0 + int(s.unplug_s * 1e9))
            alarm.set(max(wake, now + 1))
    finally:
        for s in slots:
            if s.sock is not None:
                with contextlib.suppress(OSError):
                    ep.unregister(s.sock.fileno())
                s.sock.close()
                s.sock = None
        ep.close()
        alarm.close()
    return slots
