"""The SpaceWire-style routed network (cell.snp.spacewire): addressing byte by byte, what a router
does with bad packets and loops, replies routed by their return address, exploration, failover."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from cell.snp import rmap
from cell.snp.packet import DEFAULT_LA, Header, Pid, Query, Reply, crc8, decode, encode
from cell.snp.spacewire import (
    FAILOVER_CYCLES,
    HOP_NS,
    IDENTITY_ADDR,
    IDENTITY_LEN,
    ROUTER_LA,
    End,
    Explorer,
    Network,
    Node,
    Packet,
    Redundant,
    Router,
    RouterInfo,
    cd_cycle_us,
    explore,
    failover_ms,
    parse_identity,
    ring,
    routed_reply,
)


def test_a_router_forwards_by_path_and_by_logical_address_byte_by_byte() -> None:
    r = Router(7, 4, {0x40: (3, 4)})
    # path addressing: out of port 2, the address byte deleted
    assert r.route(Packet(b"\x02\x40xyz")) == [(2, Packet(b"\x40xyz", End.EOP, 1))]
    # logical addressing: the table's first port that is up, the address byte kept
    assert r.route(Packet(b"\x40abc")) == [(3, Packet(b"\x40abc", End.EOP, 1))]
    r.up.discard(3)
    assert r.route(Packet(b"\x40abc")) == [(4, Packet(b"\x40abc", End.EOP, 1))]
    # the configuration port: what follows the 0 goes to it (Router.configure answers)
    assert r.route(Packet(b"\x00abc")) == [(0, Packet(b"abc", End.EOP, 1))]
    assert parse_identity(r.identity(2)) == RouterInfo(7, 4, 2, frozenset({1, 2, 4}))
    assert r.counters.forwarded == 3


def _identity_read(tid: int, back: bytes = b"", address: int = IDENTITY_ADDR) -> bytes:
    padded = back.rjust(-(-len(back) // 4) * 4, b"\x00")
    return rmap.encode_read(rmap.Read(ROUTER_LA, 0x42, tid, address, IDENTITY_LEN, reply_address=padded))


def test_the_configuration_port_answers_an_identity_read_by_the_way_it_came_then_its_reply_address() -> None:
    r = Router(7, 4)
    r.up.discard(3)
    [(port, pkt)] = r.configure(_identity_read(9, b"\x05\x01"), 2)
    # out of the port the read came in by, its reply address (leading zeros dropped) in front
    assert port == 2 and pkt.data[:2] == b"\x05\x01"
    ident = b"R\x07\x04\x02" + (1 << 1 | 1 << 2 | 1 << 4).to_bytes(4, "big")  # id, ports, came by, up
    head = bytes([0x42, 0x01, 0x0C, 0x00, ROUTER_LA, 0, 9, 0, 0, 0, 8])
    assert pkt.data[2:] == head + bytes([crc8(head)]) + ident + bytes([crc8(ident)])
    # anything else at the configuration port: dropped, counted
    write = rmap.encode_write(rmap.Write(ROUTER_LA, 0x42, 1, IDENTITY_ADDR, b"x" * 8))
    for bad in (b"", b"junk", write, _identity_read(10, address=4), _identity_read(11)[:-1]):
        assert r.configure(bad, 1) == []
    assert r.counters.config == 1 and r.counters.dropped["bad_config"] == 5


def test_bad_packets_and_loops_are_dropped_and_counted_never_raised() -> None:
    r = Router(1, 2, {0x40: (1,)})
    bad = [b"", b"\x05x", b"\xff", b"\x41x"]
    for data in bad:
        assert r.route(Packet(data)) == []
    assert r.route(Packet(b"\x01x", End.EEP)) == []
    r.up.discard(1)
    assert r.route(Packet(b"\x01x")) == [] and r.route(Packet(b"\x40x")) == []
    d = r.counters.dropped
    got = (d["empty"], d["bad_port"], d["reserved"], d["no_route"], d["eep"], d["link_down"])
    assert got == (1, 1, 1, 1, 1, 2) and r.counters.forwarded == 0
    # two routers whose tables send a logical address to each other: the packet goes round until
    # the hop bound, then it is dropped as a loop (it would otherwise circulate for ever)
    net = Network()
    a = net.add_router("A", Router(1, 2, {0x50: (2,)}))
    b = net.add_router("B", Router(2, 2, {0x50: (1,)}))
    net.add_node(Node("n"))
    net.link(("n", 1), ("A", 1))
    net.link(("A", 2), ("B", 1))
    assert net.send("n", 1, b"\x50hello") == []
    assert a.counters.dropped["loop"] + b.counters.dropped["loop"] == 1


def test_a_reply_finds_its_way_back_by_the_return_address() -> None:
    net, routes = ring(["m1", "m2"])
    port, path = routes["m2"][1]  # through R2
    q = encode(Header(0x21, Pid.MRT, bytes([1]), 5, 6), Query(3, 0))
    got = [d for d in net.send("master", port, path + q) if d.node == "m2"]
    assert len(got) == 1 and got[0].ns == 2 * HOP_NS and got[0].packet.data == q  # the path byte deleted
    asked = decode(got[0].packet.data)
    back = asked.header.reversed()
    assert back == Header(DEFAULT_LA, Pid.MRT, b"", 6, 5)  # processes swapped, no return address
    answer = routed_reply(asked.header, encode(back, Reply(3)))
    home = net.send("m2", got[0].port, answer)
    assert [d.node for d in home] == ["master"] and decode(home[0].packet.data).body == Reply(3)


_reads = st.tuples(st.integers(0, 0xFFFF), st.integers(0, 40), st.integers(0, 255)).map(
    lambda a: (lambda raw: raw[: a[1]] + bytes([a[2]]) + raw[a[1] + 1 :])(_identity_read(a[0], b"\x02"))
)  # (an identity read with one byte set to anything)


@given(st.binary(max_size=48) | _reads, st.integers(1, 4))
def test_nothing_at_a_configuration_port_or_back_at_an_explorer_raises(data: bytes, port: int) -> None:
    r = Router(3, 4)
    out = r.configure(data, port)
    assert out == [] or [p for p, _ in out] == [port]  # (answered by the way it came, or dropped)
    assert r.counters.config + r.counters.dropped["bad_config"] == 1
    ex = Explorer()
    ex.probes()
    ex.answer(data)
    assert ex.stray + len(ex.routers) == 1


def test_the_master_finds_the_topology_by_path_addresses() -> None:
    net, _ = ring(["m1", "m2", "m3"])
    for port, router in ((1, "router 1"), (2, "router 2")):
        assert explore(net, "master", port) == {(): router, (2,): "node m1", (3,): "node m2", (4,): "node m3"}
    net.set_link(("R1", 3), False)  # m2's link to R1 down: not found through R1, still through R2
    assert (3,) not in explore(net, "master", 1) and explore(net, "master", 2)[(3,)] == "node m2"


def test_exploration_goes_router_by_router_its_answers_routed_back_by_the_return_ports() -> None:
    """Two routers in a row and a loop between them: the second router answers by the port it was
    reached by, then back through the first by the reply address the explorer built from what the
    first said; a router met again by the loop is noted, not explored twice."""
    net = Network()
    r1, r2 = net.add_router("R1", Router(1, 4)), net.add_router("R2", Router(2, 3))
    for name in ("master", "a", "b"):
        net.add_node(Node(name))
    net.link(("master", 1), ("R1", 1))
    net.link(("R1", 2), ("R2", 3))
    net.link(("R1", 3), ("b", 1))
    net.link(("R2", 1), ("a", 1))
    net.link(("R2", 2), ("R1", 4))
    assert explore(net, "master") == {
        (): "router 1", (2,): "router 2", (3,): "node b", (4,): "router 2",
        (2, 1): "node a", (2, 2): "router 1",
    }  # fmt: skip
    # each router answered once a path reached it; the probes that reached nodes went no further
    assert r1.counters.config == 2 and r2.counters.config == 2
    assert [len(inbox) for inbox in (net.nodes["a"].inbox, net.nodes["b"].inbox)] == [1, 1]


def test_a_failed_path_is_left_for_the_other_after_the_fdir_bound() -> None:
    way = Redundant(((1, b"\x02"), (2, b"\x02")))
    assert [way.answered(False) for _ in range(FAILOVER_CYCLES)] == [False] * (FAILOVER_CYCLES - 1) + [True]
    assert way.route == (2, b"\x02") and way.failovers == 1
    assert not way.answered(True) and way.missed == 0
    ms = failover_ms()
    assert FAILOVER_CYCLES <= ms < FAILOVER_CYCLES + 1


def test_where_cd_is_computed_sets_what_the_network_adds_to_a_cycle() -> None:
    """Every message of the demonstrator crosses two hops (node, router, node): the master's [C, D]
    takes four messages in turn, the chain two and then one a module from the tip in, each module
    alone two (its neighbour's force is the cycle before's)."""
    two = 2 * HOP_NS / 1e3
    assert cd_cycle_us("master") == 4 * two
    assert cd_cycle_us("neighbour", 6) == (2 + 5) * two and cd_cycle_us("neighbour", 3) == (2 + 2) * two
    assert cd_cycle_us("local") == 2 * two
