"""`cell fuzz` against a real cell, small: every listener's inputs accounted for, nothing broken."""

from __future__ import annotations

import pytest

from cell.fuzz import strategies
from cell.fuzz.campaign import campaign
from cell.fuzz.mutate import Mutator, fix_snp_crcs
from cell.snp import packet as snp


def test_seeds_and_mutations_are_reproducible_and_crcs_are_made_right() -> None:
    a = strategies.examples(strategies.snp_packets, 50, seed_=3)
    assert a == strategies.examples(strategies.snp_packets, 50, seed_=3)
    good = []
    for raw in a:  # the seeds' CRCs are right: whatever is refused is refused past them
        try:
            snp.decode(raw)
            good.append(raw)
        except snp.PacketError as exc:
            assert "crc" not in exc.counter
    assert good
    m1, m2 = Mutator(7), Mutator(7)
    assert [m1.snp(x, a) for x in a] == [m2.snp(x, a) for x in a]
    broken = bytearray(good[0])
    broken[-1] ^= 0xFF
    broken[3 + broken[2] + 8] ^= 0xFF  # both CRCs wrong
    with pytest.raises(snp.PacketError):
        snp.decode(bytes(broken))
    snp.decode(fix_snp_crcs(bytes(broken)))


@pytest.mark.slow
async def test_a_small_campaign_breaks_nothing_and_every_input_is_accounted_for() -> None:
    only = ["skills", "dataplane", "snp", "rlink", "bus", "ur", "config", "100 MB"]
    result = await campaign(inputs=600, seed=5, only=only, log_fn=lambda _line: None)
    per = result["per_target"]
    bad = {k: v for k, v in per.items() if v.get("hangs") or v.get("crashed") or not v.get("ok")}
    assert result["crashes"] == 0 and result["hangs"] == 0, bad
    assert result["answered_in_time"] and result["ok"], per
    assert all(
        per[k]["inputs"] == 600 for k in ("skills", "dataplane", "snp", "rlink", "bus", "ur", "config")
    )
    # each skill line answered exactly once, by the error its fault earns
    assert per["skills"]["lines_answered"] == per["skills"]["lines_expected"] > 600
    assert {"malformed", "unknown_skill"} <= set(per["skills"]["codes"])
    # the datagrams' faults were counted by the services that dropped them
    assert per["dataplane"]["counted"]["rejected.kind"] > 0
    assert per["dataplane"]["counted"]["rejected.spoofed"] > 0  # statuses for the cell's own robots
    assert per["snp"]["counted"].get("bad_header_crc", 0) + per["snp"]["counted"].get("malformed", 0) > 0
    assert sum(per["rlink"]["counted"].values()) > 0
    assert sum(v for k, v in per["bus"]["counted"].items() if k.endswith("bus.malformed")) > 0
    assert per["config"]["loaded"] + per["config"]["refused"] == 600
    # every bad dashboard line answered once, every bad program refused, the RTDE session still up
    ur = per["ur"]
    assert ur["dashboard_answers"] == ur["dashboard_lines"] == 200
    assert ur["programs_refused"] == ur["programs"] == 200 and ur["rtde_alive"] == 1
    assert ur["counted"]["ur.dashboard_unknown"] == 200 and ur["counted"]["ur.scripts_refused"] == 200
    assert (
        per["100 MB line" if "100 MB line" in per else "attack: 100 MB line"]["first_reply"]
        == "line_too_long"
    )
