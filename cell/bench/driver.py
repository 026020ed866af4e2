"""The host-side robot driver of NSDI'22 App. B, the baseline of `cell bench paper`'s x86 section:
one process per arm (as the paper's ROS driver node) taking each status datagram, computing the
velocity command the obvious way (struct and floats) and sending it back.

`python -m cell.bench.driver ROBOT` serves one arm on a free UDP port of 127.0.0.1 and prints the port;
`cell bench dataplane`'s "naive" target runs the same protocol for many arms in one process.
"""

from __future__ import annotations

import asyncio
import socket
import struct
import sys
from typing import Any

from cell.robot.datagram import SCALE


class NaiveDriver(asyncio.DatagramProtocol):
    """The obvious way: one datagram at a time, struct and floats, a dict of targets."""

    STRUCT = struct.Struct("!HBBIqq")

    def __init__(self, targets: dict[int, list[float]]) -> None:
        self.targets = targets
        self.answered = 0

    def connection_made(self, transport: Any) -> None:
        self.transport = transport

    def datagram_received(self, data: bytes, addr: Any) -> None:
        if len(data) != 24:
            return
        rid, jid, kind, seq, v, p = self.STRUCT.unpack(data)
        if kind != 0:
            return
        target = self.targets.get(rid)
        vel, pos = v / SCALE, p / SCALE
        cmd = 0.0 if target is None else vel + 1.0 * (0.0 - vel) + 5.0 * (target[jid] - pos)
        cmd = max(-3.14159, min(3.14159, cmd))
        self.transport.sendto(self.STRUCT.pack(rid, jid, 1, seq, round(cmd * SCALE), p), addr)
        self.answered += 1


async def _serve_one(robot: int) -> None:
    """One arm heading for 0.1 rad on every joint, until stdin closes."""
    loop = asyncio.get_running_loop()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    transport, _ = await loop.create_datagram_endpoint(lambda: NaiveDriver({robot: [0.1] * 6}), sock=sock)
    print(sock.getsockname()[1], flush=True)
    await loop.run_in_executor(None, sys.stdin.read)
    transport.close()


if __name__ == "__main__":
    asyncio.run(_serve_one(int(sys.argv[1])))
