"""The running SnP cycle over the two routers (cell.snp.routed): return addresses put in and taken
out byte by byte, the routers' process over real sockets (paths, junk, a link cut), and the
modular arm's cycle through it with a link cut halfway along its path."""

from __future__ import annotations

import multiprocessing as mp
import random
import socket
import time

import pytest

from cell.snp import rmap
from cell.snp.link import FAILOVER_SENDS, RoutedLink, module_port, with_return, without_return
from cell.snp.native import available
from cell.snp.packet import Header, Pid, Query, decode, encode
from cell.snp.routed import explore_routers, routers_main, start_routers
from cell.snp.spacewire import IDENTITY_ADDR, IDENTITY_LEN, ROUTER_LA, Router, RouterInfo
from tests.conftest import run_unless_stolen, wait_until_quiet

native_only = pytest.mark.skipif(available() is not None, reason=f"the C cycle does not build: {available()}")


def _packet() -> bytes:
    return encode(Header(0, Pid.MRT, b"", 104, 0), Query(7, 123_456))


def test_a_return_address_goes_in_and_comes_out_byte_by_byte() -> None:
    plain = _packet()
    routed = with_return(plain, bytes([5]))
    assert len(routed) == len(plain) + 1 and routed[2:4] == b"\x01\x05"
    pkt = decode(routed)  # (a whole packet: both CRCs hold, the return address read as such)
    assert pkt.header.return_address == b"\x05" and pkt.body == decode(plain).body
    assert without_return(routed) == (plain, (5,))
    assert with_return(routed, b"\x09") == routed  # (one already there stays)
    bad = bytearray(routed)
    bad[4] ^= 0x40  # (its source process: the header CRC no longer holds)
    assert without_return(bytes(bad)) is None and without_return(b"\x00" * 5) is None


def test_a_module_link_moves_to_the_other_router_after_sends_unheard_and_refuses_strangers() -> None:
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(4)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
            s.settimeout(2.0)
        node, r1, r2, stranger = socks
        link = RoutedLink(node, (r1.getsockname(), r2.getsockname()), (3,), failover_after=FAILOVER_SENDS)
        for _ in range(FAILOVER_SENDS):
            link.send(_packet(), (1,))
            got = r1.recv(2048)
        assert got[0] == 1 and without_return(got[1:]) == (_packet(), (3,))  # the path, then its return
        link.send(_packet(), (1,))  # nothing heard back: now over R2
        assert r2.recv(2048)[0] == 1 and link.failovers == 1 and link.active == 1
        answer = with_return(_packet(), b"\x01")
        assert link.received(answer, stranger.getsockname()) is None and link.refused == 1
        assert link.received(answer, r2.getsockname()) == (_packet(), (1,)) and link.unheard == 0
    finally:
        for s in socks:
            s.close()


@pytest.mark.parametrize(
    "native", [pytest.param(True, marks=native_only, id="c"), pytest.param(False, id="python")]
)
def test_the_routers_forward_by_path_drop_junk_and_a_cut_link_counting_each(native: bool) -> None:
    nodes = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(3)]
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ctx = mp.get_context("spawn")
    here, there = ctx.Pipe()
    try:
        for s in (*nodes, stranger):
            s.bind(("127.0.0.1", 0))
            s.settimeout(2.0)
        peers = [s.getsockname() for s in nodes]  # the master on port 1, two modules on 2 and 3
        proc = ctx.Process(
            target=routers_main, args=(there, peers, time.monotonic() + 30, 0, native), daemon=True
        )
        proc.start()
        r1, r2 = here.recv()
        nodes[0].sendto(b"\x03" + _packet(), r1[0])  # master -> R1 port 3 -> module 2
        assert nodes[2].recv(2048) == _packet()  # (the path byte deleted)
        nodes[1].sendto(b"\x01" + _packet(), r2[1])  # module 1 -> R2 -> master
        assert nodes[0].recv(2048) == _packet()
        stranger.sendto(b"\x01" + _packet(), r1[1])  # not on the link: dropped
        nodes[0].sendto(b"\x09" + _packet(), r1[0])  # a port R1 does not have
        # the configuration port: an identity read answered as spacewire.Router answers it, byte
        # for byte (out of the port it came in by, its reply address in front); junk counted
        for node, at, back in ((0, r1[0], b""), (1, r2[1], b"\x00\x00\x00\x07")):
            read = rmap.encode_read(
                rmap.Read(ROUTER_LA, 0x42, 5, IDENTITY_ADDR, IDENTITY_LEN, reply_address=back)
            )
            nodes[node].sendto(b"\x00" + read, at)
            router = Router(1 + (at == r2[1]), 3)
            assert nodes[node].recv(2048) == router.configure(read, 1 + node)[0][1].data
        nodes[0].sendto(b"\x00junk", r1[0])
        here.send(("cut", 0, 3))
        assert here.recv() == ("cut", 0, 3)  # (done before what follows)
        nodes[0].sendto(b"\x03" + _packet(), r1[0])  # out of the cut port: lost
        nodes[2].sendto(b"\x01" + _packet(), r1[2])  # in at it: lost
        nodes[0].sendto(b"\x03" + _packet(), r2[0])  # the other router's way still goes
        assert nodes[2].recv(2048) == _packet()
        here.send(("stop", 0, 0))
        assert here.poll(10)
        counts = here.recv()
        assert counts["dropped"] == 2  # the stranger's, and what came in on the cut link
        assert counts["R1"]["dropped.bad_port"] == 1 and counts["R1"]["dropped.link_down"] == 1
        assert counts["R1"]["forwarded"] == 1 and counts["R2"]["forwarded"] == 2
        assert counts["R1"]["config"] == 1 and counts["R2"]["config"] == 1
        assert counts["R1"]["dropped.bad_config"] == 1
        proc.join(10)
    finally:
        for s in (*nodes, stranger):
            s.close()


@pytest.mark.parametrize(
    "native", [pytest.param(True, marks=native_only, id="c"), pytest.param(False, id="python")]
)
def test_the_master_finds_its_port_and_its_modules_by_exploring_the_running_routers(native: bool) -> None:
    """Nothing declared but its two links: it learns the port it is on and the ports up beyond, a
    link cut before it looks missing from that router's and found through the other's."""
    from cell.ports import free_ports

    master = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    modules = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(3)]
    for s, port in zip((master, *modules), free_ports(4), strict=True):
        s.bind(("127.0.0.1", port))
    modules[2].settimeout(2.0)
    ports = [s.getsockname()[1] for s in modules]
    ctx = mp.get_context("spawn")
    routers = start_routers(ctx, master.getsockname()[1], ports, time.monotonic() + 30, native=native)
    try:
        routers.cut(0, module_port(1))
        found = explore_routers(master, routers.master)
        assert found.own == (1,) and found.ends == ((2,), (3,), (4,))
        assert found.routers == (
            RouterInfo(1, 4, 1, frozenset({1, 2, 4})),
            RouterInfo(2, 4, 1, frozenset({1, 2, 3, 4})),
        )
        # a probe that reached a module is nothing it takes: a router's configuration read
        assert modules[2].recv(2048)[:2] == bytes([0, ROUTER_LA])
    finally:
        counts = routers.stop()
        for s in (master, *modules):
            s.close()
    assert counts["R1"]["config"] == 1 and counts["R2"]["config"] == 1 and counts["dropped"] == 0


# (make perf: its aims hold only on a machine whose timers wake on time; on a VM whose idle vCPUs stall
# a wake-up for milliseconds several times a second it fails as it did before issue 53's work: p99.9 of
# a 1 ms clock_nanosleep 2-12 ms there, measured the day it was moved)
@pytest.mark.perf
@pytest.mark.slow
@pytest.mark.parametrize(
    ("in_c", "period"),
    [
        pytest.param(True, 1_000_000, marks=native_only, id="c-1ms"),
        # (six Python modules' exchanges take 3.5-4 ms of a 4 ms cycle's slots: a slower hour of this
        # host missed 58-68 % of them there, routed or not, and 0.04 % at 8 ms)
        pytest.param(False, 8_000_000, id="python-8ms"),
    ],
)
def test_the_arms_cycle_runs_over_the_routers_and_fails_over_a_cut_link(in_c: bool, period: int) -> None:
    """The master and six modules over the two routers (the cycle and the routers in C, or all in
    Python), the master given nothing but its links; the MuJoCo arm on a joint move; module 4's
    link to R1 cut halfway: it goes over R2 after FAILOVER_CYCLES missed."""
    from cell.bench.snp import failover_in_cycle_ms
    from cell.bench.snp_trial import SLOT_NS, cycle_figures, trial
    from cell.modular.cycle import SETTLE_NS
    from cell.modular.reference import Q_HOME, joint_move
    from cell.snp.modular import CycleConfig
    from cell.snp.runner import chain
    from cell.snp.spacewire import FAILOVER_CYCLES

    ref = joint_move(Q_HOME, Q_HOME + 0.3, 1.5)
    seconds = 1.2 + SETTLE_NS / 1e9 + ref.t[-1]
    scale = period // 1_000_000
    config = CycleConfig(
        period_ns=period, budget_ns=period, slot_ns=SLOT_NS * scale, management_ns=400_000 * scale
    )
    slots = chain(6, random.Random(2))
    cut_id = slots[3]["module_id"]

    def run() -> dict:
        wait_until_quiet()  # (eight processes' cycles on this machine's cores: not the last test's teardown)
        r = trial(
            slots, seconds, config=config, native=in_c, reference=ref, routed=True, cut=(seconds / 2, 3)
        )
        # the master found its modules' paths by exploring the routers, each router answering it once
        assert r["master"]["explored"] == [[2 + k] for k in range(6)]
        assert r["routers"]["R1"]["config"] == 1 and r["routers"]["R2"]["config"] == 1
        # the cut module ended on R2 (at 1 ms a stall of the master's core now and then moves every
        # module over together: counted, not a fault of the path)
        cut_module = next(m for m in r["modules"] if m["module_id"] == cut_id)
        assert cut_module["failovers"] >= 1 and cut_module["router"] == 1
        assert r["routers"]["R2"]["forwarded"] > 100 and len(r["tool_error_mm"]) == len(ref.t)
        return r

    def timing(r: dict) -> str | None:
        f = cycle_figures(r, period)
        took = failover_in_cycle_ms(r, cut_id)
        if f.modules_ran != 6 or f.tsp_offset_us_max >= 200.0:  # (clocks synced through the routers)
            return f"modules ran {f.modules_ran}, clock offsets up to {f.tsp_offset_us_max:.0f} us"
        if took is None or took > (FAILOVER_CYCLES + 2) * period / 1e6:
            return f"the cut module's first whole cycle came {took} ms after the cut"
        if r["tool_error_mm"].max() >= 5.0:
            return f"tool error up to {r['tool_error_mm'].max():.2f} mm"
        return None

    def disturbed(r: dict) -> str | None:
        """The modules not cut missing more than 5 % of their cycles: the host ran the cycle late."""
        others = [m["cycles"] for m in r["modules"] if m["module_id"] != cut_id]
        share = 100 * sum(int((c[:, 3] > 0).sum()) for c in others) / max(1, sum(len(c) for c in others))
        return f"the modules not cut missed in {share:.1f} % of their cycles" if share > 5.0 else None

    run_unless_stolen(run, timing, disturbed=disturbed)
