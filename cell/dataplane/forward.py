"""Ordinary traffic through the data plane: UDP port forwarding, as the paper's switch did for its
background traffic (Sec. 7.1: "the switch applied simple port forwarding").

A rule takes every datagram that arrives on its `listen` address and sends it
on to `to`, unchanged, from the same socket, through the data plane's egress
port when it has one (cell.dataplane.egress) as the `bulk` class, else at
once.  Datagrams come in bursts of equal size (UDP GRO) and leave the same
way (GSO).  A wake-up takes at most `budget` bursts, so that robot statuses
never wait behind a flood for long.
"""

from __future__ import annotations

import time

from cell.config import ForwardRule, parse_host_port
from cell.dataplane.egress import BULK, EgressPort
from cell.robot import udp


class Forwarder:
    def __init__(self, rule: ForwardRule, budget: int = 4) -> None:
        self.sock = udp.open_socket(*parse_host_port(rule.listen))
        self.to = parse_host_port(rule.to)
        self.name = rule.listen
        self.budget = budget
        self.received = self.sent = self.dropped = 0

    def _send(self, data: memoryview, seg: int, addr: tuple) -> int:
        n = udp.send_segments(self.sock, data, seg, addr)
        self.sent += n
        return n

    def handle(self, egress: EgressPort | None) -> int:
        """Forward up to `budget` bursts waiting; return how many bursts were taken."""
        for taken in range(self.budget):
            got = udp.recv_batch(self.sock)
            if got is None:
                return taken
            data, seg, _sender, _stamp = got
            seg = max(seg, 1)
            count = -(-len(data) // seg)
            self.received += count
            if egress is None:
                self.dropped += count - self._send(memoryview(data), seg, self.to)
                continue
            now, whole = time.monotonic_ns(), len(data) - len(data) % seg
            for run, size in ((data[:whole], seg), (data[whole:], len(data) - whole)):  # a short last: alone
                if run:
                    fit = egress.enqueue(BULK, run, size, self.to, self._send, now)
                    self.dropped += len(run) // size - fit
        return self.budget

    def close(self) -> None:
        self.sock.close()
