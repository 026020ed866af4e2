"""cell.ports: free ports below the kernel's ephemeral range, never one taken, never one twice."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from cell import ports


def test_ports_are_below_the_ephemeral_range_distinct_and_bindable() -> None:
    first = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    got = ports.free_ports(50) + [ports.free_port() for _ in range(50)]
    assert len(set(got)) == len(got)
    assert all(ports.LOW <= p < min(ports.HIGH, first) for p in got)
    assert not {29999, 30001, 30002, 30003, 30004} & set(got)  # (UR's standard ports stay a cell's)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", got[0]))  # (free: nothing here holds it)


def test_a_block_is_consecutive_and_skips_a_port_someone_holds(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ports, "_given", set())  # (not what the run's other tests were given)
    base = ports.free_block(4)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as held:
        held.bind(("127.0.0.1", base + 10))  # in every block of the pool but its last
        monkeypatch.setattr(ports, "_pool", lambda: range(base + 8, base + 15))
        assert ports.free_block(4) == base + 11
        with pytest.raises(RuntimeError, match="no 4 consecutive free ports"):
            ports.free_block(4)  # (the rest is held, or handed out already)
