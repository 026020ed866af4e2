"""The fault campaign: what the cell promises under each fault, and one campaign against a real cell."""

from __future__ import annotations

import json

from cell.chaos.campaign import campaign
from cell.chaos.faults import PROMISES, catalogue


def test_every_fault_has_the_promises_its_targets_call_for() -> None:
    faults = {f.name: f for f in catalogue(["r1", "r2"])}
    for service in ("bus", "dataplane", "robots", "controller", "skills", "snp", "recorder", "rlink"):
        assert f"kill:{service}" in faults
    assert {"bus-gone", "controller-link", "mute:r2", "kill:dataplane+controller"} <= set(faults)
    for f in faults.values():
        assert set(f.promises) <= set(PROMISES)
        assert {"answered", "completed", "no_lunge", "recovered"} <= set(f.promises)
    assert "stop_windows" in faults["kill:dataplane"].promises  # robots stop on their own watchdog
    assert "answered_1s" in faults["kill:dataplane"].promises and "answered_1s" in faults["mute:r2"].promises
    assert "packet_path" in faults["kill:controller"].promises  # the packet path must not notice
    assert "packet_path" not in faults["kill:robots"].promises
    assert "status" not in faults["controller-link"].promises  # nothing restarts there


async def test_a_campaign_on_the_default_cell_holds_its_promises() -> None:
    rows: list[str] = []
    result = await campaign(1, ["kill:dataplane"], log_fn=rows.append)
    assert list(result["per_fault"]) == ["kill:dataplane", "kill:dataplane+controller"]
    assert result["faults"] == 2 and result["failed"] == 0, rows
    dp = result["per_fault"]["kill:dataplane"]
    assert dp["held"] == 1 and max(dp["detect_ms"]) < 100  # the robots stopped on their own, at once
    assert dp["moved_after_rest_mrad"] < 2.0 and dp["stop_ms_max"] <= 32.0
    json.dumps(result)  # the figures are machine-readable as they are
