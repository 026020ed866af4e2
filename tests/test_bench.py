"""The benchmarks' harnesses, run small: they must measure what they claim (not the figures themselves)."""

from __future__ import annotations

import pytest

from cell.bench import bus, dataplane


@pytest.mark.slow
def test_dataplane_bench_answers_every_status_of_a_small_load() -> None:
    t = dataplane.trial("dataplane", robots=5, seconds=0.5)
    assert t["sent"] == 5 * 6 * 250  # 250 ticks of 2 ms
    assert t["answered"] == t["sent"] and t["ok"]
    assert 0 < t["p50_us"] < 8000


@pytest.mark.slow
def test_bus_bench_delivers_everything_it_counts() -> None:
    r = bus.run(messages=5_000, pings=50, rounds=1)
    for variant in ("raw_multipart", "raw_1frame", "raw_1frame_via_forwarder", "bus"):
        tp = r["throughput"][variant]
        assert tp["received"] == 5_000 and tp["lost"] == 0, variant
    assert r["throughput"]["bus"]["gaps"] == 0
    assert r["round_trip"]["bus"]["count"] == 50
    assert r["round_trip"]["bus_request_reply"]["p50_us"] > 0
