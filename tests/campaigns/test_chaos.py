"""The fault campaign: what the cell promises under each fault, and one campaign against a real cell."""

from __future__ import annotations

import asyncio
import json
from collections import deque

import numpy as np
import pytest

from cell.chaos.campaign import campaign
from cell.chaos.faults import PROMISES, catalogue
from cell.chaos.observer import Observer


def test_every_fault_has_the_promises_its_targets_call_for() -> None:
    faults = {f.name: f for f in catalogue(["r1", "r2", "r3"], ur_robots=("r3",))}
    for service in ("bus", "dataplane", "robots", "controller", "skills", "snp", "recorder", "rlink"):
        assert f"kill:{service}" in faults
    assert {"bus-gone", "controller-link", "mute:r2", "kill:dataplane+controller"} <= set(faults)
    # r3 is reached through the daemon: its UR controller goes away (the cable an emulated arm's is)
    assert "ur-controller-gone:r3" in faults and "mute:r3" not in faults
    assert "answered_1s" in faults["ur-controller-gone:r3"].promises
    for f in faults.values():
        assert set(f.promises) <= set(PROMISES)
        assert {"answered", "completed", "no_lunge", "recovered"} <= set(f.promises)
    assert "stop_windows" in faults["kill:dataplane"].promises  # robots stop on their own watchdog
    assert "answered_1s" in faults["kill:dataplane"].promises and "answered_1s" in faults["mute:r2"].promises
    assert "packet_path" in faults["kill:controller"].promises  # the packet path must not notice
    assert "packet_path" not in faults["kill:robots"].promises
    assert "status" not in faults["controller-link"].promises  # nothing restarts there


def test_on_the_xdp_backend_the_kernel_answers_while_the_data_planes_process_is_down() -> None:
    """The dataplane service is only the XDP program's control plane: the robots must not stop."""
    faults = {f.name: f for f in catalogue(["r1", "r2"], in_kernel=True)}
    for name in ("kill:dataplane", "hang:dataplane", "kill:dataplane+controller"):
        assert "kernel_answers" in faults[name].promises and "stop_windows" not in faults[name].promises
    assert not any("kernel_answers" in f.promises for f in catalogue(["r1", "r2"]))
    # the switch's port down: every robot's cable at once, they stop on their watchdogs
    assert {"answered_1s", "stop_windows"} <= set(faults["switch-down"].promises)
    assert "packet_path" not in faults["switch-down"].promises
    assert "switch-down" not in {f.name for f in catalogue(["r1", "r2"])}
    # its program detached: answered through from user space and attached again, the robots never notice
    assert {"reattached", "packet_path"} <= set(faults["xdp-detached"].promises)
    assert "stop_windows" not in faults["xdp-detached"].promises


def test_truth_that_arrives_out_of_order_is_judged_by_its_own_times() -> None:
    """After a reconnection the forwarder drains the old connection's backlog while the new one brings
    fresh samples: a motion's last samples arrive after its rest.  That is no lunge."""
    t = np.arange(0, 300) * 10_000_000
    q = np.minimum(t / 2e9, 1.0)  # moves for 2 s, then rests at 1 rad
    qd = np.where(t < 2e9, 0.5, 0.0)
    samples = [(int(ti), float(v), np.full(6, qi), False) for ti, qi, v in zip(t, q, qd, strict=True)]
    arrival = samples[:50] + [x for pair in zip(samples[50:150], samples[200:], strict=True) for x in pair]
    arrival += samples[150:200]
    obs = Observer.__new__(Observer)
    obs.truth = {"r1": deque(arrival)}
    obs.newest = {"r1": max(arrival, key=lambda s: s[0])}
    moved, _, _ = obs.lunge("r1", 0, int(t[-1]))
    assert moved < 1e-9
    assert obs.latest("r1")[0] == t[-1]
    shuffled = Observer.__new__(Observer)  # and a real lunge is still seen in a shuffled arrival
    back = [
        (ti, 0.5, np.full(6, 1.0 - (ti - 3e9) / 2e9), False)
        for ti in range(3_000_000_000, 4_000_000_000, 10**7)
    ]
    shuffled.truth = {"r1": deque(arrival + back)}
    assert shuffled.lunge("r1", 0, 4_000_000_000)[0] > 0.4


@pytest.mark.slow
async def test_a_campaign_on_the_default_cell_holds_its_promises() -> None:
    rows: list[str] = []
    result = await campaign(1, ["kill:dataplane"], log_fn=rows.append)
    assert list(result["per_fault"]) == ["kill:dataplane", "kill:dataplane+controller"]
    assert result["faults"] == 2 and result["failed"] == 0, rows
    dp = result["per_fault"]["kill:dataplane"]
    assert dp["held"] == 1 and max(dp["detect_ms"]) < 100  # the robots stopped on their own, at once
    assert dp["moved_after_rest_mrad"] < 2.0 and dp["stop_ms_max"] <= 34.0  # 3+1 windows of 8 ms, a tick
    json.dumps(result)  # the figures are machine-readable as they are
    # progress: what it will take, then a line per fault as it is judged
    assert rows[0].startswith("2 faults x 1 round(s): about ") and rows[1].startswith("[1/2] ")
    assert rows[2].startswith("[2/2] ") and "kill:dataplane+controller" in rows[2]


def test_an_estop_is_judged_by_the_robots_truth_against_their_braking() -> None:
    """Each robot must stand within its braking from the speed it had (+ ESTOP_MARGIN_MS) of the order,
    by its truth; with the hub down no order gets through, and the link's watchdog must stop it."""
    from cell.chaos.campaign import ESTOP_MARGIN_MS, Campaign
    from cell.chaos.faults import Fault, Kill
    from cell.chaos.observer import EStop
    from cell.config import load_config

    config = load_config(None)
    robots = [r.name for r in config.robots]

    def camp_with(stop_after_ms: dict[str, float], order_ns: int) -> Campaign:
        """Robots at 0.5 rad/s until stop_after_ms past the order, then at rest (10 ms truth)."""
        obs = Observer.__new__(Observer)
        obs.truth = {}
        for r in robots:
            t = np.arange(order_ns - 500_000_000, order_ns + 3_000_000_000, 10_000_000)
            qd = np.where(t < order_ns + stop_after_ms[r] * 1e6, 0.5, 0.0)
            obs.truth[r] = deque((int(ti), float(v), np.zeros(6), False) for ti, v in zip(t, qd, strict=True))
        camp = Campaign.__new__(Campaign)
        camp.config, camp.obs, camp.robots = config, obs, robots
        return camp

    bound = 0.5 / 5.0 * 1e3 + ESTOP_MARGIN_MS  # the UR5e's joints brake at 5 rad/s^2
    fault = Fault("kill:vision", (Kill("vision"),), ())
    t0, order = 1_000_000_000_000, 1_001_200_000_000
    order_heard = EStop(order, {r: 120.0 for r in robots})
    ok, why = camp_with({r: bound - 20 for r in robots}, order)._estop_held(
        fault, order_heard, t0, order + 2 * 10**9
    )
    assert ok, why
    late = {r: bound - 20 for r in robots} | {robots[0]: bound + 40}
    ok, why = camp_with(late, order)._estop_held(fault, order_heard, t0, order + 2 * 10**9)
    assert not ok and why.startswith("by the order"), why
    # ... unless the hypervisor held the cell's CPUs back as long meanwhile (steal: the host's doing)
    stolen = EStop(order, {r: 120.0 for r in robots}, stolen_ms=50.0)
    ok, why = camp_with(late, order)._estop_held(fault, stolen, t0, order + 2 * 10**9)
    assert ok and "50 of them stolen" in why, why
    # the hub killed: no report, the robots stand by the link's watchdog ([rlink] watchdog_s x 1.25)
    hub = Fault("kill:rlink", (Kill("rlink"),), ())
    unheard = EStop(order, {}, "robot(s) [1, 2] did not report still within 5.0 s")
    watchdog = t0 + int(config.rlink.watchdog_s * 1.25e9)
    ok, why = camp_with({r: (watchdog - order) / 1e6 + bound - 20 for r in robots}, order)._estop_held(
        hub, unheard, t0, order + 2 * 10**9
    )
    assert ok and why.startswith("by the link's watchdog"), why

    # the bus down before the order: the last truth heard 1.2 s before it said 0.2 rad/s, the first
    # after it (10 ms on) 0.5: the arm sped up meanwhile, and its bound is from 0.55 rad/s (0.5 plus
    # what 10 ms of braking sheds), not from 0.2 (110 ms: it would have failed the first arm below)
    def unheard_before(stands_ms: float) -> Campaign:
        camp = camp_with({r: stands_ms for r in robots}, order)
        for r in robots:
            t = np.arange(order - 2_000_000_000, order + 3_000_000_000, 10_000_000)
            t = t[(t <= order - 1_200_000_000) | (t > order)]
            qd = np.where(t < order, 0.2, np.where(t < order + stands_ms * 1e6, 0.5, 0.0))
            camp.obs.truth[r] = deque(
                (int(ti), float(v), np.zeros(6), False) for ti, v in zip(t, qd, strict=True)
            )
        return camp

    bus = Fault("kill:bus", (Kill("bus"),), ())
    ok, why = unheard_before(0.5 / 5.0 * 1e3 + 20)._estop_held(bus, order_heard, t0, order + 2 * 10**9)
    assert ok and "bound 170 ms" in why, why
    ok, why = unheard_before(0.55 / 5.0 * 1e3 + ESTOP_MARGIN_MS + 20)._estop_held(
        bus, order_heard, t0, order + 2 * 10**9
    )
    assert not ok, why  # (standing 20 ms past that bound)


async def test_each_action_does_what_it_says_to_a_real_process_and_its_end_undoes_it() -> None:
    """Hang stops a process until its end continues it, Kill kills it, SlowLink slows the link and its
    end restores it; an end twice is harmless (the campaign ends every action again on its way out)."""
    import subprocess

    from cell.bus.delay import DelayLink
    from cell.chaos.faults import LINK, Hang, Kill, SlowLink
    from cell.config import load_config

    def state(pid: int) -> str:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0]

    class Cell:  # what an action acts on (faults.Target)
        config = load_config(None)
        link = DelayLink(config.bus, "tcp://127.0.0.1:1", "tcp://127.0.0.1:2", 0.0, 0.0)

        def switch_port(self, *setting: str) -> None:
            raise AssertionError("no switch here")

    cell = Cell()
    proc = subprocess.Popen(["sleep", "30"])
    try:
        pids = {"svc": proc.pid}
        hang = Hang("svc", 1.0)
        await hang.inject(cell, pids)
        for _ in range(200):  # (the signal is delivered asynchronously)
            if state(proc.pid) == "T":
                break
            await asyncio.sleep(0.005)
        assert state(proc.pid) == "T"
        hang.end(cell, pids)
        hang.end(cell, pids)
        for _ in range(200):
            if state(proc.pid) != "T":
                break
            await asyncio.sleep(0.005)
        assert state(proc.pid) in ("S", "R")
        await Kill("svc").inject(cell, pids)
        assert proc.wait(timeout=5) == -9
        Hang("svc").end(cell, pids)  # (its process gone: nothing to continue, no error)
    finally:
        proc.kill()
        proc.wait()
    slow = SlowLink("controller", 4.0)
    await slow.inject(cell, {})
    assert (cell.link.delay, cell.link.jitter, cell.link.loss) == LINK
    slow.end(cell, {})
    assert (cell.link.delay, cell.link.jitter, cell.link.loss) == (0.0, 0.0, 0.0)
