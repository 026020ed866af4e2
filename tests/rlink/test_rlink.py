"""The Responsive Link, sans IO: packets byte by byte, CRC, FEC, routing table, a node's overtaking."""

from __future__ import annotations

import asyncio
import itertools
import socket
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cell.rlink import fec
from cell.rlink.link import MAX_CLIENTS, SLICE, LinkPorts, NodeLink
from cell.rlink.node import Node
from cell.rlink.packet import (
    DATA_SIZE,
    EVENT_SIZE,
    MAX_HOPS,
    EventType,
    Kind,
    Packet,
    PacketError,
    crc16,
    decode,
    encode,
)
from cell.rlink.routing import Route, RoutingTable
from tests.conftest import free_port

E, D = Kind.EVENT, Kind.DATA


def crc16_bitwise(data: bytes) -> int:
    """CRC-16/CCITT-FALSE as a shift register, bit by bit: the reference for the table-driven one."""
    crc = 0xFFFF
    for byte in data:
        for i in range(7, -1, -1):
            top = (crc >> 15) ^ (byte >> i & 1)
            crc = (crc << 1) & 0xFFFF
            if top:
                crc ^= 0x1021
    return crc


def test_crc16_is_ccitt_false() -> None:
    assert crc16(b"123456789") == 0x29B1  # the catalogued check value
    assert crc16(b"") == 0xFFFF
    for data in (b"\x00", b"\xff" * 60, bytes(range(62))):
        assert crc16(data) == crc16_bitwise(data)


def test_an_event_packet_byte_by_byte() -> None:
    p = Packet(E, dst=3, src=1, priority=3, type=EventType.ESTOP, seq=7, payload=b"\x01\x02")
    raw = encode(p)
    body = bytes([3, 1, 0b11_0_00001, 7]) + b"\x01\x02" + bytes(6) + bytes([MAX_HOPS, 2])
    assert raw == body + struct.pack(">H", crc16_bitwise(body))
    assert len(raw) == EVENT_SIZE == 16
    assert decode(raw) == p


def test_a_data_packet_byte_by_byte() -> None:
    payload = bytes(range(56))
    p = Packet(D, dst=200, src=9, priority=1, type=17, seq=255, payload=payload, hops=2)
    raw = encode(p)
    body = bytes([200, 9, 0b01_1_10001, 255]) + payload + bytes([2, 56])
    assert raw == body + struct.pack(">H", crc16_bitwise(body))
    assert len(raw) == DATA_SIZE == 64
    assert decode(raw, D) == p


@pytest.mark.parametrize(
    ("raw", "reason"),
    [
        (b"", "truncated"),
        (bytes(15), "truncated"),
        (bytes(40), "truncated"),
        (bytes(65), "oversized"),
        (bytes(1500), "oversized"),
    ],
)
@pytest.mark.parametrize("link", [None, "event"])
def test_wrong_sizes_are_refused_by_reason(raw: bytes, reason: str, link: str | None) -> None:
    if link == "event" and len(raw) == 40:
        reason = "oversized"  # on an event link anything over 16 bytes is
    with pytest.raises(PacketError) as info:
        decode(raw, None if link is None else E)
    assert info.value.reason == reason


def test_corruption_a_wrong_kind_and_a_bad_length_are_refused() -> None:
    good = encode(Packet(E, 2, 1, 0, EventType.BEACON, 0, b"abc"))
    for i in range(len(good)):  # any byte changed: the CRC says so
        bad = bytearray(good)
        bad[i] ^= 0x10
        with pytest.raises(PacketError, match="crc"):
            decode(bytes(bad))
    with pytest.raises(PacketError) as info:
        decode(good, D)  # an event packet on the data link
    assert info.value.reason == "kind"
    body = bytearray(good[:-2])
    body[2] |= 0x20  # a 16-byte packet whose header says data
    with pytest.raises(PacketError) as info:
        decode(bytes(body) + crc16(body).to_bytes(2, "big"))
    assert info.value.reason == "kind"
    body = bytearray(good[:-2])
    body[-1] = 9  # an event payload is 8 bytes at most
    with pytest.raises(PacketError) as info:
        decode(bytes(body) + crc16(body).to_bytes(2, "big"))
    assert info.value.reason == "length"


@settings(max_examples=400)
@given(st.binary(max_size=200))
def test_no_bytes_make_decode_fail_any_other_way(raw: bytes) -> None:
    try:
        decode(raw)
    except PacketError as exc:
        assert exc.reason in {"truncated", "oversized", "crc", "kind", "length"}


def test_out_of_range_fields_cannot_be_made() -> None:
    with pytest.raises(ValueError, match="priority"):
        Packet(E, 1, 1, 4, 0, 0)
    with pytest.raises(ValueError, match="8 bytes"):
        Packet(E, 1, 1, 0, 0, 0, bytes(9))


# --- FEC ---------------------------------------------------------------------------------------------


def test_every_single_bit_error_is_corrected_and_every_double_detected() -> None:
    for nibble in range(16):
        word = int(fec.ENCODE[nibble])
        for bit in range(8):
            data, fixed = fec.recover(bytes([word ^ 1 << bit, int(fec.ENCODE[0])]))
            assert data == bytes([nibble]) and fixed == 1
        for a, b in itertools.combinations(range(8), 2):
            with pytest.raises(fec.Uncorrectable):
                fec.recover(bytes([word ^ 1 << a ^ 1 << b, int(fec.ENCODE[0])]))


def test_the_codewords_are_an_extended_hamming_code() -> None:
    words = [int(w) for w in fec.ENCODE]
    assert len(set(words)) == 16
    assert min(bin(a ^ b).count("1") for a, b in itertools.combinations(words, 2)) == 4  # SEC-DED


def test_a_packet_survives_one_flipped_bit_per_codeword() -> None:
    raw = encode(Packet(D, 5, 6, 2, 3, 4, bytes(range(56))))
    line = bytearray(fec.protect(raw))
    assert len(line) == 2 * DATA_SIZE
    for i in range(len(line)):
        line[i] ^= 1 << (i % 8)
    data, fixed = fec.recover(bytes(line))
    assert data == raw and fixed == len(line)


# --- routing -----------------------------------------------------------------------------------------


def test_routes_match_by_source_destination_and_priority_later_over_earlier() -> None:
    t = RoutingTable([Route(links=(1,)), Route(links=(0,), dst=5), Route(links=(2, 3), dst=5, priority=3)])
    assert t.lookup(E, 9, 1, 0) == (0b00010, 0)  # the catch-all
    assert t.lookup(D, 9, 5, 1) == (0b00001, 1)  # to this node's host
    assert t.lookup(E, 9, 5, 3) == (0b01100, 3)  # urgent ones go two ways: multicast
    t.remove(dst=5)
    assert t.lookup(E, 9, 5, 3) == (0, 3)  # changed at run time: no route now


def test_event_and_data_take_their_own_routes_and_priorities_are_rewritten() -> None:
    t = RoutingTable(
        [
            Route(links=(1,), data=False),  # EE only
            Route(links=(2,), event=False),  # DE only (over the first, for data)
            Route(links=(1,), src=7, event=True, data=False, new_priority=3),  # PE: promoted
        ]
    )
    assert t.lookup(E, 1, 1, 0) == (0, 0)  # the second route disabled events everywhere
    assert t.lookup(D, 1, 1, 0) == (0b100, 0)
    assert t.lookup(E, 7, 1, 0) == (0b010, 3)
    with pytest.raises(ValueError, match="links"):
        Route(links=(5,))


# --- a node --------------------------------------------------------------------------------------------


def chain_node(address: int, **kw) -> Node:
    """A node of a daisy chain: its own address to its host (L0), everything else on to L1."""
    return Node(address, RoutingTable([Route(links=(1,)), Route(links=(0,), dst=address)]), **kw)


def drain(node: Node, link: int) -> list[tuple[Kind, Packet]]:
    out = []
    while (got := node.next_out(link)) is not None:
        out.append(got)
    return out


def test_events_overtake_data_and_higher_priorities_lower_ones() -> None:
    n = chain_node(1)
    for i in range(5):
        n.send(D, dst=2, type=0, payload=bytes([i]), priority=3)
    n.send(E, dst=2, type=EventType.BEACON, priority=0)
    n.send(E, dst=2, type=EventType.ESTOP, priority=3)
    n.send(D, dst=2, type=0, payload=b"late", priority=0)
    order = [(k, p.type, p.priority, p.payload) for k, p in drain(n, 1)]
    assert order[:2] == [(E, EventType.ESTOP, 3, b""), (E, EventType.BEACON, 0, b"")]
    assert [o[3] for o in order[2:]] == [bytes([i]) for i in range(5)] + [b"late"]  # FIFO within one


def test_a_packet_crosses_a_daisy_chain_and_each_hop_counts() -> None:
    a, b, c = chain_node(1), chain_node(2), chain_node(3)
    sent = a.send(E, dst=3, type=EventType.ESTOP, payload=b"r1", priority=3)
    _, p = a.next_out(1)  # a -> b on L1 ...
    b.receive(2, E, a.wire(1, p))  # ... arriving on b's L2
    _, p = b.next_out(1)
    c.receive(2, E, b.wire(1, p))
    ((kind, got),) = drain(c, 0)  # delivered to c's host
    assert (kind, got.src, got.type, got.payload) == (E, 1, EventType.ESTOP, b"r1")
    assert got.hops == sent.hops - 2 and got.seq == sent.seq
    assert drain(b, 0) == []  # not for b's host


def test_a_full_queue_drops_the_least_urgent_and_counts_it() -> None:
    n = chain_node(1, depth=4)
    for i in range(4):
        n.send(E, dst=2, type=EventType.BEACON, payload=bytes([i]), priority=0)
    n.send(E, dst=2, type=EventType.ESTOP, priority=3)  # room is made: the newest beacon goes
    n.send(E, dst=2, type=EventType.BEACON, payload=b"x", priority=0)  # nothing lower: this one goes
    assert n.links[1].overflow[E] == 2
    out = [(p.type, p.payload) for _, p in drain(n, 1)]
    assert out == [(EventType.ESTOP, b"")] + [(EventType.BEACON, bytes([i])) for i in range(3)]
    assert n.links[1].depth_max[E] == 4


def test_bad_packets_are_counted_by_reason_and_the_node_goes_on() -> None:
    n = chain_node(1)
    good = encode(Packet(E, 2, 9, 1, EventType.STOP, 0))
    n.receive(2, E, b"\x00" * 3)
    n.receive(2, E, good + b"!")
    n.receive(2, E, good[:-1] + bytes([good[-1] ^ 1]))
    n.receive(2, D, good)  # an event packet on the data link: 16 bytes there are too short
    n.receive(2, E, encode(Packet(E, 2, 9, 1, EventType.STOP, 0, hops=0)))
    lonely = Node(1, RoutingTable([Route(links=(0,), dst=1)]))  # knows no way to node 2
    lonely.receive(2, E, good)
    assert {k: v for k, v in n.drops.items() if v} == {
        "truncated": 1,
        "oversized": 1,  # 17 bytes on an event link
        "crc": 1,
        "kind": 1,  # a whole event packet on the data link
        "hops": 1,
    }
    assert lonely.drops["no_route"] == 1
    assert n.links[2].packets_in == [4, 1]
    n.receive(2, E, good)  # and it still forwards
    ((kind, p),) = drain(n, 1)
    assert (kind, p.type, p.hops) == (E, EventType.STOP, MAX_HOPS - 1)


def test_a_packet_never_goes_back_the_way_it_came() -> None:
    n = Node(1, RoutingTable([Route(links=(0, 1, 2, 3, 4))]))  # broadcast
    n.receive(2, E, encode(Packet(E, 255, 9, 0, EventType.BEACON, 0)))
    assert [n.pending(link) for link in range(5)] == [1, 1, 0, 1, 1]


def test_over_a_lossy_line_fec_corrects_and_drops_what_it_cannot() -> None:
    a = chain_node(1, fec_links=frozenset({1}))
    b = chain_node(2, fec_links=frozenset({2}))
    a.send(D, dst=2, type=1, payload=b"state", priority=1)
    _, p = a.next_out(1)
    line = bytearray(a.wire(1, p))
    assert len(line) == 2 * DATA_SIZE
    line[10] ^= 0x04  # one bit: corrected
    b.receive(2, D, bytes(line))
    ((_, got),) = drain(b, 0)
    assert got.payload == b"state" and b.links[2].fec_corrected == 1
    line[20] ^= 0x06  # two bits in one codeword: detected, dropped
    b.receive(2, D, bytes(line))
    assert b.drops["fec"] == 1 and drain(b, 0) == []


@settings(max_examples=300)
@given(link=st.integers(1, 4), kind=st.sampled_from([E, D]), raw=st.binary(max_size=300))
def test_a_node_takes_any_bytes_without_raising(link: int, kind: Kind, raw: bytes) -> None:
    n = chain_node(1, fec_links=frozenset({3}))
    n.receive(link, kind, raw)
    assert sum(n.drops.values()) + n.pending(1) + n.pending(0) == 1


# --- nodes on UDP sockets ------------------------------------------------------------------------------


def udp() -> tuple[str, int]:
    return ("127.0.0.1", free_port(socket.SOCK_DGRAM))


def pair(on_b_event, on_b_data=None) -> tuple[NodeLink, NodeLink]:
    """Node 1's L1 wired to node 2's L2 over loopback, each routing its own address to its host."""
    a_ev, a_da, b_ev, b_da = udp(), udp(), udp(), udp()
    a = NodeLink(chain_node(1), [LinkPorts(1, a_ev, a_da, b_ev, b_da)])
    b_node = Node(2, RoutingTable([Route(links=(2,)), Route(links=(0,), dst=2)]))
    b = NodeLink(b_node, [LinkPorts(2, b_ev, b_da, a_ev, a_da)], on_event=on_b_event, on_data=on_b_data)
    return a, b


async def test_an_event_round_trip_between_two_nodes() -> None:
    replies: asyncio.Queue[Packet] = asyncio.Queue()

    def echo(p: Packet) -> None:
        if p.type == EventType.ECHO:
            b.send(E, dst=p.src, type=EventType.ECHO_REPLY, payload=p.payload, priority=p.priority)

    a, b = pair(echo)
    a.on_event = replies.put_nowait
    try:
        async with asyncio.timeout(5), asyncio.TaskGroup() as tg:
            tasks = [tg.create_task(a.run()), tg.create_task(b.run())]
            for i in range(20):
                a.send(E, dst=2, type=EventType.ECHO, payload=i.to_bytes(4, "big"), priority=2)
                got = await replies.get()
                assert (got.type, got.src, int.from_bytes(got.payload, "big")) == (EventType.ECHO_REPLY, 2, i)
            for t in tasks:
                t.cancel()
    finally:
        a.close()
        b.close()
    assert len(b.event_latency_ns) == 20 and b.node.links[2].packets_in[E] == 20


async def test_an_event_overtakes_a_data_backlog_at_the_receiver() -> None:
    """2,000 data packets wait in node 2's data socket when an e-stop arrives: it is handed over
    before more than one slice of them has been."""
    seen: list[tuple[str, int]] = []
    data_so_far = 0

    def on_data(batch: list[Packet]) -> None:
        nonlocal data_so_far
        data_so_far += len(batch)

    a, b = pair(lambda p: seen.append(("event", data_so_far)), on_data)
    try:
        for i in range(2000):  # queued in b's socket: b's loop is not running yet
            a.send(D, dst=2, type=1, payload=i.to_bytes(4, "big"))
        a.send(E, dst=2, type=EventType.ESTOP, priority=3)
        async with asyncio.timeout(5):
            task = asyncio.create_task(b.run())
            while data_so_far < 2000 or not seen:
                await asyncio.sleep(0.001)
            task.cancel()
    finally:
        a.close()
        b.close()
    assert seen == [("event", seen[0][1])] and seen[0][1] <= SLICE
    assert b.node.links[2].packets_in == [1, 2000] and sum(b.node.drops.values()) == 0


async def test_junk_on_every_socket_is_counted_and_the_node_goes_on() -> None:
    got: list[Packet] = []
    a, b = pair(got.append)
    try:
        junk = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for kind in (E, D):
            for raw in (
                b"",
                b"x" * 15,
                b"y" * 70,
                bytes(5000),
                encode(Packet(E, 2, 9, 0, 1, 0))[:-1] + b"\0",
            ):
                junk.sendto(raw, b.address(2, kind))
        junk.close()
        async with asyncio.timeout(5):
            task = asyncio.create_task(b.run())
            while sum(b.node.drops.values()) < 10:
                await asyncio.sleep(0.001)
            a.send(E, dst=2, type=EventType.STOP, priority=1)  # and it still delivers
            while not got:
                await asyncio.sleep(0.001)
            task.cancel()
    finally:
        a.close()
        b.close()
    assert got[0].type == EventType.STOP
    drops = {k: v for k, v in b.node.drops.items() if v}
    assert drops == {"truncated": 4, "oversized": 4, "crc": 2}, drops  # a broken packet is a CRC drop first


async def test_the_host_interface_answers_at_most_max_clients_and_still_takes_the_rest() -> None:
    """A peer sending from many ports cannot make every event cost a copy to each of them."""
    at_a: list[Packet] = []
    a_ev, a_da, b_ev, b_da, host = udp(), udp(), udp(), udp(), udp()
    a = NodeLink(chain_node(1), [LinkPorts(1, a_ev, a_da, b_ev, b_da)], on_event=at_a.append)
    b_node = Node(2, RoutingTable([Route(links=(2,)), Route(links=(0,), dst=2)]))
    b = NodeLink(b_node, [LinkPorts(2, b_ev, b_da, a_ev, a_da)], host=host)
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(MAX_CLIENTS + 8)]
    try:
        async with asyncio.timeout(5), asyncio.TaskGroup() as tg:
            tasks = [tg.create_task(a.run()), tg.create_task(b.run())]
            for i, s in enumerate(socks):  # each a client of b's host interface, sending to node 1
                s.bind(("127.0.0.1", 0))
                s.setblocking(False)
                s.sendto(encode(Packet(E, 1, 2, 1, EventType.NOP, i % 256)), host)
                while len(at_a) <= i:  # (one at a time: a burst would overflow the link's event queue)
                    await asyncio.sleep(0.001)
            a.send(E, dst=2, type=EventType.STOP, priority=3)  # an event for b's host: copied to clients
            while not b.node.links[0].packets_out[E]:
                await asyncio.sleep(0.001)
            for t in tasks:
                t.cancel()
        heard = []
        for s in socks:
            try:
                heard.append(len(s.recv(256)) > 0)
            except BlockingIOError:
                heard.append(False)
    finally:
        a.close()
        b.close()
        for s in socks:
            s.close()
    assert len(at_a) == MAX_CLIENTS + 8  # every client's event went on its way
    assert len(b.clients) == MAX_CLIENTS and b.clients_refused == 8
    assert sum(heard) == MAX_CLIENTS and not any(heard[MAX_CLIENTS:])  # the refused hear nothing back
