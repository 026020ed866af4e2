"""SnP packets, the handler (sans IO) and the snp service, byte by byte and end to end."""

from __future__ import annotations

import asyncio
import dataclasses
import random
import socket
import struct
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cell.bus import Bus
from cell.snp.client import DeadlineMissed, QueryDenied, SnpClient
from cell.snp.handler import Handler
from cell.snp.packet import (
    Cancel,
    Denial,
    Denied,
    ErrorReply,
    Header,
    Item,
    PacketError,
    PacketType,
    Pid,
    PidQuery,
    PidReply,
    Quantity,
    Query,
    Refusal,
    Reply,
    TimeRequest,
    TimeResponse,
    Wanted,
    crc8,
    decode,
    encode,
    item_id,
)
from cell.snp.state import CellState
from cell.v1 import snp_pb2
from tests.conftest import free_port, run_unless_stolen


def crc_bitwise(data: bytes) -> int:
    """The RMAP CRC the long way: shift register, x^8 + x^2 + x + 1, each byte LSB first."""
    reg = 0
    for byte in data:
        for bit in range(8):
            inbit = (byte >> bit) & 1
            top = (reg >> 7) & 1
            reg = (reg << 1) & 0xFF
            if top ^ inbit:
                reg ^= 0x07
    # the register holds the CRC with its bits reversed (LSB-first convention)
    return int(f"{reg:08b}"[::-1], 2)


def test_crc_vectors() -> None:
    assert crc8(b"") == 0
    assert crc8(b"\x01") == 0x91  # by hand: 0x01 -> 0xE0 0x70 0x38 0x1C 0x0E 0x07 0xE3 0x91
    assert crc_bitwise(b"\x01") == 0x91
    rng = random.Random(5)
    for n in (1, 2, 7, 64):
        data = bytes(rng.randrange(256) for _ in range(n))
        assert crc8(data) == crc_bitwise(data)
        assert crc8(data + bytes([crc8(data)])) == 0  # a reflected CRC over data and its CRC is 0


def test_a_cancellation_packet_byte_by_byte() -> None:
    h = Header(destination=0xFE, pid=Pid.MRT, return_address=b"\x05", source_process=1, destination_process=2)
    got = encode(h, Cancel(7))
    head = bytes([0xFE, 0xF0, 0x01, 0x05]) + struct.pack("!II", 1, 2)
    data = bytes([0x00, 0x00, 0x04]) + struct.pack("!I", 7)
    assert got == head + bytes([crc_bitwise(head)]) + data + bytes([crc_bitwise(data)])
    pkt = decode(got)
    assert (
        pkt.header == h and pkt.body == Cancel(7) and pkt.type == PacketType.TIME_BOUNDED_QUERY_CANCELLATION
    )


def test_every_body_round_trips() -> None:
    h = Header(1, Pid.MRT, b"", 3, 4)
    q = Query(9, 10**18, (Item(item_id(1, 1, 0), 0.25, 5),), (Wanted(item_id(1, 2, 5), 6),))
    assert decode(encode(h, q)).body == q
    # cargo layout of a query: id, deadline, inputs (count, id, f32, u64), outputs (count, id, u64)
    cargo = decode(encode(h, q)).raw_cargo
    assert cargo == struct.pack("!IQIIfQIIQ", 9, 10**18, 1, item_id(1, 1, 0), 0.25, 5, 1, item_id(1, 2, 5), 6)
    for body in (Reply(9, (Item(1, 2.5, 3),)), Denied(9, Denial.CANCELLED)):
        assert decode(encode(h, body)).body == body
    th = Header(1, Pid.TSP)
    assert decode(encode(th, TimeRequest(5))).body == TimeRequest(5)
    assert decode(encode(th, TimeResponse(5, 6, 7))).body == TimeResponse(5, 6, 7)
    ph = Header(1, Pid.PID_MANAGEMENT)
    assert decode(encode(ph, PidQuery(0xF0), type=PacketType.PID_SUPPORTED_QUERY)).body == PidQuery(0xF0)
    assert decode(encode(ph, PidReply((0xF0, 0xF1)))).body == PidReply((0xF0, 0xF1))


def test_error_paths() -> None:
    good = bytearray(encode(Header(1, Pid.MRT, b"\x09", 3, 4), Cancel(1)))
    bad_head = bytearray(good)
    bad_head[12] ^= 0xFF  # the header CRC
    with pytest.raises(PacketError) as info:
        decode(bytes(bad_head))
    assert info.value.reply is None and info.value.counter == "bad_header_crc"  # dropped: no trusted return
    bad_data = bytearray(good)
    bad_data[-1] ^= 0x55
    with pytest.raises(PacketError) as info:
        decode(bytes(bad_data))
    reply = info.value.reply
    assert reply is not None and reply.type == PacketType.INVALID_DATA_CRC_REPLY
    assert reply.header.destination_process == 3 and reply.header.source_process == 4  # back to the sender
    with pytest.raises(PacketError) as info:
        decode(encode(Header(1, 0x77), Cancel(1), type=PacketType.TIME_BOUNDED_QUERY_CANCELLATION))
    assert info.value.reply is not None and info.value.reply.type == PacketType.UNKNOWN_PID_REPLY
    assert info.value.reply.body == ErrorReply(0x77)
    with pytest.raises(PacketError) as info:
        decode(encode(Header(1, Pid.MRT), Cancel(1), type=0x0999))
    assert info.value.reply is not None and info.value.reply.body == ErrorReply(0x0999)
    # a cargo cut short (with valid CRCs): malformed, dropped
    head = bytes([1, 0xF0, 0]) + struct.pack("!II", 0, 0)
    data = bytes([0, 0, 1]) + b"\x00\x00"
    with pytest.raises(PacketError) as info:
        decode(head + bytes([crc8(head)]) + data + bytes([crc8(data)]))
    assert info.value.reply is None and info.value.counter == "malformed"


def _valid_packets() -> list[bytes]:
    h, ph, th = Header(1, Pid.MRT, (3, 7)), Header(1, Pid.PID_MANAGEMENT), Header(1, Pid.TSP)
    q = Query(9, 10**18, (Item(item_id(1, 1, 0), 0.25, 5),), (Wanted(item_id(1, 2, 5), 6),))
    return [
        encode(Header(1, Pid.MRT), q),
        encode(h, q),
        encode(h, Reply(9, (Item(1, 2.5, 3), Item(2, -1.0, 4)))),
        encode(h, Denied(9, Denial.CANCELLED)),
        encode(h, Cancel(9)),
        encode(ph, PidQuery(0xF0), type=PacketType.PID_SUPPORTED_QUERY),
        encode(ph, PidReply((0xF0, 0xF1))),
        encode(th, TimeRequest(5)),
        encode(th, TimeResponse(5, 6, 7)),
    ]


def _changed(data: bytes, at: int, value: int, cut: int) -> bytes:
    """data with one byte set, then cut short by `cut` bytes."""
    b = bytearray(data)
    b[at % len(b)] = value
    return bytes(b[: len(b) - cut])


DATAGRAMS = st.one_of(
    st.binary(max_size=80),  # (mostly a bad header: dropped early)
    st.sampled_from(_valid_packets()),  # (each kind taken: decoded, encoded back)
    st.builds(
        _changed,
        st.sampled_from(_valid_packets()),
        st.integers(0, 80),
        st.integers(0, 255),
        st.integers(0, 4),
    ),  # (a valid one with a byte changed or its tail cut)
)


@settings(max_examples=500)
@given(DATAGRAMS)
def test_any_datagram_is_a_packet_that_encodes_back_or_a_counted_refusal(data: bytes) -> None:
    """decode fails only with PacketError, counted under a Refusal, its reply (if any) an error
    reply; what it takes is a packet whose encoding decodes to the same packet (bytes for bytes:
    a NaN among the items is still the same bytes)."""
    try:
        p = decode(data)
    except PacketError as exc:
        assert exc.counter in set(Refusal) and (exc.reply is None or isinstance(exc.reply.body, ErrorReply))
        return
    again = encode(p.header, p.body, type=p.type)
    q = decode(again)
    assert (q.header, q.type, type(q.body)) == (p.header, p.type, type(p.body))
    assert encode(q.header, q.body, type=q.type) == again


# --- the handler, sans IO ----------------------------------------------------------------------------


class Clock:
    def __init__(self) -> None:
        self.t = 10**18

    def __call__(self) -> int:
        return self.t


def state_with_history(clock: Clock) -> CellState:
    st = CellState(offset_ns=0)
    st.add_robot(1, 6)
    for k in range(11):  # 1 rad/s on joint 0 for 100 ms, sampled every 10 ms
        t = clock.t - 100_000_000 + k * 10_000_000
        q = np.zeros(6)
        q[0] = k * 0.01
        qd = np.zeros(6)
        qd[0] = 1.0
        st.observe(1, t, q, qd, qd)
    return st


def ask(handler: Handler, body: object, pid: int = Pid.MRT, type: int | None = None) -> list:
    out = handler.receive(encode(Header(1, pid, b"", 7, 0), body, type=type), ("peer", 1))  # type: ignore[arg-type]
    return [decode(d).body for d, _ in out]


def test_queries_past_and_future_values_denials_and_edf() -> None:
    clock = Clock()
    h = Handler(state_with_history(clock), clock)
    pos = item_id(1, Quantity.POSITION, 0)
    now = clock.t
    assert (
        ask(h, Query(1, now + 10**7, (), (Wanted(pos, now - 55_000_000), Wanted(pos, now + 20_000_000))))
        == []
    )
    (data, to) = h.serve()  # type: ignore[misc]
    reply = decode(data).body
    assert isinstance(reply, Reply) and to == ("peer", 1)
    past, future = reply.items
    assert past.value == pytest.approx(0.045, abs=1e-6)  # interpolated from the history
    assert future.value == pytest.approx(0.1 + 0.02, abs=1e-6)  # extrapolated: 1 rad/s for 20 ms
    # denials: unknown output item, unknown input item, a deadline that cannot be met
    assert ask(h, Query(2, now + 10**7, (), (Wanted(item_id(9, 1, 0), now),))) == [
        Denied(2, Denial.UNKNOWN_OUTPUT_ITEM)
    ]
    assert ask(h, Query(3, now + 10**7, (Item(item_id(1, 9, 0), 0.0, now),), ())) == [
        Denied(3, Denial.UNKNOWN_INPUT_ITEM)
    ]
    assert ask(h, Query(4, now + 1000, (), (Wanted(pos, now),))) == [Denied(4, Denial.DEADLINE_CANNOT_BE_MET)]
    # earliest deadline first, and a cancellation takes a pending query back
    for qid, dl in ((10, now + 9 * 10**6), (11, now + 3 * 10**6), (12, now + 6 * 10**6)):
        assert ask(h, Query(qid, dl, (), (Wanted(pos, now),))) == []
    assert ask(h, Cancel(12)) == [Denied(12, Denial.CANCELLED)]
    order = []
    while (out := h.serve()) is not None:
        order.append(decode(out[0]).body.query_id)  # type: ignore[union-attr]
    assert order == [11, 10]
    # one whose deadline passed while it waited is denied when its turn comes
    assert ask(h, Query(13, now + 5 * 10**6, (), (Wanted(pos, now),))) == []
    clock.t += 10 * 10**6
    (data, _) = h.serve()  # type: ignore[misc]
    assert decode(data).body == Denied(13, Denial.DEADLINE_CANNOT_BE_MET)
    assert h.counters.denied["deadline_cannot_be_met"] == 2 and h.counters.cancelled == 1


def test_time_and_pid_requests() -> None:
    clock = Clock()
    h = Handler(state_with_history(clock), clock)
    assert ask(h, TimeRequest(123), pid=Pid.TSP) == [TimeResponse(123, clock.t, clock.t)]
    assert ask(h, PidQuery(0), pid=Pid.PID_MANAGEMENT, type=PacketType.PID_LIST_QUERY) == [
        PidReply((0xF0, 0xF1, 0xF2))
    ]
    assert ask(h, PidQuery(0xF1), pid=Pid.PID_MANAGEMENT, type=PacketType.PID_SUPPORTED_QUERY) == [
        PidReply((0xF1,))
    ]
    assert ask(h, PidQuery(0x42), pid=Pid.PID_MANAGEMENT, type=PacketType.PID_SUPPORTED_QUERY) == [
        PidReply(())
    ]
    # a valid packet the handler does not take (a reply) is answered as an unknown type
    assert ask(h, Reply(1, ())) == [ErrorReply(PacketType.TIME_BOUNDED_QUERY_REPLY)]


# --- the service ---------------------------------------------------------------------------------------


async def test_the_snp_service_answers_about_a_moving_robot(start_cell) -> None:
    robots = [{"id": 1, "name": "r1", "skill_port": free_port(), "backend": "kinematic", "truth_hz": 100}]
    cell = await start_cell(run=["bus", "dataplane", "robots", "controller", "snp"], robots=robots)
    host, port = cell.config.snp.listen.split(":")
    async with SnpClient((host, int(port))) as snp, Bus.connect(cell.config.bus, "watcher") as bus:
        offset, delay = await snp.sync_time()
        assert abs(offset) < 2_000_000 and 0 < delay < 10_000_000  # one host: the clocks agree
        assert set(await snp.pids()) == {0xF0, 0xF1, 0xF2} and await snp.supports(0xF1)
        denials = await bus.subscribe("events/snp/denial")
        pos = item_id(1, Quantity.POSITION, 1)
        async with asyncio.timeout(10):
            while True:  # until the handler has heard the robot's truth
                try:
                    got = await snp.query([(pos, snp.now() - 20_000_000)], deadline=snp.now() + 20_000_000)
                    break
                except QueryDenied:
                    await asyncio.sleep(0.05)
        assert got[pos].value == pytest.approx(-1.5708, abs=1e-3)
        with pytest.raises(QueryDenied) as info:
            await snp.query([(item_id(7, 1, 0), snp.now())], query_id=4242)
        assert info.value.explanation == Denial.UNKNOWN_OUTPUT_ITEM
        async with asyncio.timeout(5):  # every denial also goes on the bus (for viewers and logs)
            while True:
                d = (await denials.recv(timeout=5)).decode(snp_pb2.SnpDenial)
                if d.query_id == 4242:
                    break
        assert d.explanation == Denial.UNKNOWN_OUTPUT_ITEM
        # junk of every kind does not stop it
        sock_junk = [b"", b"\x00", bytes(range(40)), encode(Header(1, 0x33), Cancel(1), type=4)]
        for j in sock_junk:
            snp.send_raw(j)
        # many queries: each answered before its deadline or denied.  This VM (and this test's own
        # loop, which shares 2 cores with the cell) stalls for milliseconds now and then, so a few
        # answers may come too late or not at all: counted, as a guessing asker would, and bounded
        answered = denied = missed = late = 0
        for _ in range(300):
            try:
                t0 = time.time_ns()
                await snp.query([(pos, snp.now())], deadline=snp.now() + 3_000_000)
                answered += 1
                late += time.time_ns() - t0 >= 3_000_000 + 2_000_000
            except QueryDenied:
                denied += 1
            except DeadlineMissed:
                missed += 1
        # every query accounted for; how many meet their deadline is the machine's load and a bench's
        # figure (`cell bench snp`, `make perf`), not this test's
        assert answered + denied + missed == 300 and answered > 0, (answered, denied, missed, late)


@pytest.mark.parametrize("native", [False, True], ids=["python-modules", "c-modules"])
def test_the_modular_robot_bench_trial_accounts_for_every_query(native: bool) -> None:
    import random

    from cell.bench.snp_trial import cycle_figures, trial
    from cell.snp.native import available
    from cell.snp.runner import chain

    if native and available() is not None:
        pytest.skip(f"the C cycle does not build here: {available()}")

    def run() -> dict:
        r = trial(chain(2, random.Random(3)), seconds=1.5, native=native)
        assert {m["module_id"] for m in r["modules"]} == {101, 102}
        assert sorted(m["joint"] for m in r["modules"]) == [0, 1]  # configured by the chain
        h = r["master"]["handler"]
        denied = sum(v for k, v in h.items() if k.startswith("denied."))
        ran = sum(len(m["cycles"]) for m in r["modules"])
        assert h["replies"] + denied == h["queries"]  # each answered or denied, none left
        # two queries a cycle (a miss is not retried), but for a cycle cut short by the next one's start
        # before its second (an overrun; a slow day's run was 9 short), and those in flight at the end
        overruns = sum(m["overruns"] for m in r["modules"])
        assert h["queries"] >= 2 * ran - overruns - 4
        two_step = all(m["two_step_link"] for m in r["modules"])  # (the kernel gives transmit stamps)
        assert not two_step or (cycle_figures(r).tsp_two_step and r["master"]["counters"]["follow_ups"] > 0)
        # the master stopped with the modules (it had run on 0.5 s, guessing and then excluding them;
        # a module may still be excluded mid-run, when this VM stalls a process for 50 ms)
        end = max(int(m["cycles"][-1, 2]) for m in r["modules"])  # (the master's clock is the host's)
        assert [t - end for t, what, _, _ in r["master"]["events"] if what == "lost" and t > end] == []
        return r

    def timing(r: dict) -> str | None:
        f = cycle_figures(r)
        # (most exchanges answered in time: a broken cycle misses them all; the share is the bench's
        # figure); the modules started up to 2 ms off, and two-step links are servoed to the kernel's
        # stamps (one-step: 20-50 us)
        bound = 10 if all(m["two_step_link"] for m in r["modules"]) else 2000
        if f.cycles <= 500 or f.modules_ran != 2 or f.missed_pct >= 50.0 or f.tsp_offset_us_max >= bound:
            offsets = f"offsets up to {f.tsp_offset_us_max:.0f} us"
            return f"{f.cycles} cycles of {f.modules_ran} modules, {f.missed_pct:.1f} % missed, {offsets}"
        return None

    run_unless_stolen(run, timing)


def test_the_robots_cycle_spans_every_modules_exchanges_in_a_period() -> None:
    import numpy as np

    from cell.bench.snp_trial import CycleFigures, _robot_cycles

    # (scheduled, T1, end, missed) per cycle of two modules; period 2 lacks module b: not counted
    a = np.array([[1_000_000, 1_000_010, 1_300_000, 0], [2_000_000, 2_000_000, 2_200_000, 0]])
    b = np.array([[1_000_000, 1_000_050, 1_500_000, 0], [3_000_000, 3_000_000, 3_100_000, 0]])
    assert _robot_cycles([a, b], 2).tolist() == [(1_500_000 - 1_000_010) / 1e6]
    f = CycleFigures(10, 2, 0.1, 0.9, 0.2, 0.9, 1.0, 5.0, 0.5, 0.1, 0.5, True, 0, 0, 0.4, 0.5)
    assert f.meets_aim
    assert not dataclasses.replace(f, cycle_ms_p99=1.1).meets_aim
    assert not dataclasses.replace(f, missed_pct=1.0).meets_aim


def test_the_cycles_packet_shapes_are_the_full_codecs_bytes_and_refuse_anything_else() -> None:
    from cell.snp.packet import query_shape, reply_shape

    h = Header(0, Pid.MRT, b"", 101, 7)
    q = Query(5, 10**12, (Item(0x100, 0.5, 1000), Item(0x200, -1.25, 1000)), (Wanted(0x300, 2000),))
    r = Reply(5, (Item(0x300, 0.75, 2000),))
    full_q = encode(h, q, PacketType.TIME_BOUNDED_QUERY)  # (a type given: the general encoder)
    full_r = encode(h, r, PacketType.TIME_BOUNDED_QUERY_REPLY)
    qs, rs = query_shape(2, 1), reply_shape(1)
    assert (
        qs.pack(0, Pid.MRT, 101, 7, 5, 10**12, (0x100, 0.5, 1000, 0x200, -1.25, 1000), (0x300, 2000))
        == full_q
    )
    assert rs.pack(0, Pid.MRT, 101, 7, 5, (0x300, 0.75, 2000)) == full_r == encode(h, r)
    f = qs.parse(full_q)
    assert f is not None and (f[3], f[8], f[9], f[12], f[15], f[18]) == (101, 5, 10**12, 0.5, -1.25, 0x300)
    assert rs.parse(full_r) is not None and rs.parse(full_r)[11] == 0.75
    bad = bytearray(full_q)
    bad[-2] ^= 1  # data CRC now wrong
    assert qs.parse(bytes(bad)) is None and query_shape(1, 1).parse(full_q) is None
    assert rs.parse(full_q) is None and qs.parse(full_r) is None  # another type, another size
    with_rab = encode(Header(0, Pid.MRT, b"\x05", 101, 7), q)
    assert qs.parse(with_rab) is None and decode(with_rab).body == decode(full_q).body  # the full path


def _answering(sock: socket.socket, hold_s: float) -> None:
    """A handler of one query on `sock`: its reply, `hold_s` after the query came."""
    data, addr = sock.recvfrom(65536)
    q = decode(data)
    assert isinstance(q.body, Query)
    time.sleep(hold_s)  # (the handler's own lateness: what the test is about)
    items = tuple(Item(w.id, 1.5, w.timestamp) for w in q.body.outputs)
    sock.sendto(encode(Header(0, Pid.MRT, b"", 0, 1), Reply(q.body.query_id, items)), addr)


@pytest.mark.parametrize("hold_ms, in_time", [(0, True), (15, False)])
async def test_whether_an_answer_came_in_time_is_its_arrivals_not_when_the_client_read_it(
    hold_ms: int, in_time: bool
) -> None:
    """A client held up past a query's deadline (a busy host) with the answer waiting in its socket:
    an answer that arrived in time is no miss, one that arrived late is one, whichever the client's
    event loop runs first when it wakes (its timer or the socket)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as handler:
        handler.bind(("127.0.0.1", 0))
        async with SnpClient(handler.getsockname()) as snp:
            answering = asyncio.get_running_loop().run_in_executor(None, _answering, handler, hold_ms / 1e3)
            query = asyncio.ensure_future(snp.query([(7, snp.now())], deadline=snp.now() + 5_000_000))
            await asyncio.sleep(0)  # (the query sent)
            # this client held up (its loop blocked, as a busy host's scheduler would): its deadline
            # and the reply's arrival pass meanwhile
            time.sleep(0.03)  # noqa: ASYNC251
            if in_time:
                got = await query
                assert got[7].value == 1.5
            else:
                with pytest.raises(DeadlineMissed, match=r"arrived \d+ us after its deadline"):
                    await query
            await answering
