"""Free ports on loopback for benches, tests and a cell's own helper processes.

A port found by binding to port 0 and letting go comes from the kernel's ephemeral range, where any
socket bound to port 0 or connecting out (a router's, ZeroMQ's, a client's) may take it again before
its owner binds it: a rare "Address already in use" in a test.  So these are picked at random below
that range, away from the ports a cell uses by default (UR's 29999-30004, the cell's 50000s), each
checked free by a bind, and never handed out twice by one process.
"""

from __future__ import annotations

import random
import socket
from pathlib import Path

LOW, HIGH = 10_000, 29_900  # below UR's standard ports and (here: 32768-60999) the ephemeral range
_given: set[int] = set()
_rng = random.Random()


def _pool() -> range:
    """[LOW, HIGH) less what of it the kernel hands out as ephemeral ports."""
    try:
        first, _ = map(int, Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
    except (OSError, ValueError):
        first = 32_768
    return range(LOW, max(LOW + 1_000, min(HIGH, first)))


def _bindable(ports: range, kind: int, host: str) -> bool:
    socks: list[socket.socket] = []
    try:
        for p in ports:
            s = socket.socket(socket.AF_INET, kind)
            socks.append(s)
            s.bind((host, p))
        return True
    except OSError:
        return False
    finally:
        for s in socks:
            s.close()


def free_block(n: int, kind: int = socket.SOCK_DGRAM, host: str = "127.0.0.1") -> int:
    """The first of n consecutive ports free now (e.g. [rlink] port, the first of its PORTS)."""
    pool = _pool()
    for _ in range(500):
        base = _rng.randrange(pool.start, pool.stop - n + 1)
        block = range(base, base + n)
        if _given.isdisjoint(block) and _bindable(block, kind, host):
            _given.update(block)
            return base
    raise RuntimeError(f"no {n} consecutive free ports in {pool.start}-{pool.stop - 1}")


def free_port(kind: int = socket.SOCK_STREAM, host: str = "127.0.0.1") -> int:
    """One port free now (TCP unless kind says otherwise)."""
    return free_block(1, kind, host)


def free_ports(n: int, kind: int = socket.SOCK_DGRAM, host: str = "127.0.0.1") -> list[int]:
    """n ports free now, not necessarily consecutive (UDP unless kind says otherwise)."""
    return [free_block(1, kind, host) for _ in range(n)]
