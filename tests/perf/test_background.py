"""Fig. 14 in network namespaces (cell.bench.background), reduced: the 1,280-byte frames at 1.8x the
port's rate, once through one shared FIFO and once with strict priority for the robots."""

from __future__ import annotations

import os
import subprocess

import pytest

from cell.bench import background as bg
from tests.conftest import wait_until_quiet

pytestmark = [pytest.mark.perf, pytest.mark.skipif(bg.available() is not None, reason=str(bg.available()))]


@pytest.mark.slow
def test_a_congested_port_delays_and_drops_robot_commands_in_a_fifo_and_not_under_priority() -> None:
    def at_rate(r: bg.Result) -> bool:
        return all(
            row.offered_mbps > 0.9 * 1.8 * r.rate_mbps
            and 0.8 * r.rate_mbps < row.forwarded_mbps < 1.02 * r.rate_mbps
            for row in r.rows
        )

    # the software switch (the data plane's Python packet path, on one core) forwards 100 Mbit/s
    # with little to spare on this VM: in its slow phases a trial forwarded 74-77 (3 of 14 trials
    # one day, before the SnP changes of that day as after them): the first of three trials, each
    # once the machine is quiet, whose port ran at its rate is the one checked, as in test_fleet
    for _ in range(3):
        wait_until_quiet()
        lines: list[str] = []
        r = bg.run(loads=(1.8,), frames=(1280,), seconds=1.0, log=lines.append)
        if at_rate(r):
            break
    fifo, prio = (next(x for x in r.rows if x.scheduling == s) for s in ("fifo", "priority"))
    for row in (fifo, prio):  # the generator offered the load, and the port ran at (about) its rate
        assert row.offered_mbps > 0.9 * 1.8 * r.rate_mbps
        assert 0.8 * r.rate_mbps < row.forwarded_mbps < 1.02 * r.rate_mbps
    # one FIFO: the robots' commands wait behind a full 3 ms buffer, and some find it full
    assert fifo.p50_us > 2000 and fifo.lost_fraction > 0.01, fifo
    # strict priority: none lost at the port, and no queue to wait in (this machine's floor stays)
    assert prio.lost_fraction < 0.001, prio
    assert prio.p50_us < fifo.p50_us - 1000, (prio, fifo)
    assert any("robot commands dropped at the port 0," in line for line in lines if "(priority)" in line)
    # and the namespaces it made are gone
    names = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, timeout=10).stdout
    assert f"cbg{os.getpid() % 100000}" not in names
