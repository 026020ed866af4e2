"""SpW-SnP-MR beyond the queries: initialisation packets, RMAP, SnP-TSP, the modular robot.

The state machines run here on simulated time (a network that delivers every datagram after
a fixed latency), so that exploration, configuration, FDIR and the clock servo are checked
exactly; tests/test_snp_runner-like checks on real UDP sockets are at the end."""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable

import pytest

from cell.snp import rmap
from cell.snp.master import Master
from cell.snp.modular import CycleConfig, ModuleState
from cell.snp.module import JointModule
from cell.snp.packet import (
    Configure,
    Configured,
    Header,
    NodeInfo,
    NodeInfoQuery,
    PacketError,
    PacketType,
    Pid,
    PidReply,
    TimeBeacon,
    TimeFollowUp,
    TimeRequest,
    TimeResponse,
    TimeSubscribe,
    TimeSubscribed,
    crc8,
    decode,
    encode,
    follow_up,
    stamp_departure,
)
from cell.snp.tsp import MIN_PERIOD_NS, BeaconSchedule, ClockServo, Oscillator
from tests.conftest import snp_master_on_loopback

# --- the new packets, byte by byte ---------------------------------------------------------------


def test_initialisation_and_tsp_packets_round_trip_and_have_the_documented_layout() -> None:
    h = Header(0x20, Pid.MRT, b"", 7, 9)
    for body in (
        NodeInfoQuery(),
        NodeInfo(101, 2, 0, 1, (0x000100, 0x000200), 0xFF),
        Configure(3, 1_000_000, 0, 1_000_000, (20.0, 0.5)),
        Configured(3, 0),
        TimeSubscribe(10_000_000, 20_000),
        TimeSubscribed(10_000_000, 50_000),
        TimeBeacon(5, 1_234_567_890_123),
        TimeFollowUp(PacketType.TIME_BEACON, 5, 1_234_567_890_999),
    ):
        assert decode(encode(h, body)).body == body
    raw = encode(Header(0, Pid.TSP, b"", 0, 0), TimeBeacon(1, 0x0102030405060708))
    head = bytes([0, 0xF1, 0]) + bytes(8)
    assert raw[: len(head)] == head and raw[len(head)] == crc8(head)
    data = raw[len(head) + 1 :]
    assert data[:3] == bytes([0, 0x00, 0x14])  # reserved, TIME_BEACON
    assert data[3:-1] == bytes([0, 0, 0, 1, 1, 2, 3, 4, 5, 6, 7, 8])
    assert data[-1] == crc8(data[:-1])
    info = encode(h, NodeInfo(0x01020304, 2, 0x0A0B0C0D, 1, (0xAABBCCDD,), 3))
    cargo = info[3 + 8 + 1 + 3 : -1]
    assert cargo == bytes([1, 2, 3, 4, 2, 0xA, 0xB, 0xC, 0xD, 1, 3, 0, 1, 0xAA, 0xBB, 0xCC, 0xDD])


def test_pid_replies_say_to_what_level() -> None:
    raw = encode(Header(pid=Pid.PID_MANAGEMENT), PidReply((0xF0, 0xF1), (2, 1)))
    assert raw[-6:-1] == bytes([2, 0xF0, 2, 0xF1, 1])  # count, then (pid, level) pairs
    assert decode(raw).body == PidReply((0xF0, 0xF1), (2, 1))
    assert PidReply((0xF0,)).levels == (2,)  # FULL unless said
    with pytest.raises(ValueError):
        PidReply((0xF0,), (1, 2))


def test_malformed_initialisation_packets_are_refused_not_raised() -> None:
    raw = bytearray(encode(Header(), Configure(1, 1000, 0, 1000, (1.0,))))
    raw[-2] ^= 0xFF  # inside the cargo: data CRC now wrong
    with pytest.raises(Exception) as exc:
        decode(bytes(raw))
    assert getattr(exc.value, "counter", "") == "bad_data_crc"
    short = encode(Header(), NodeInfo(1, 2, 0, 1, (5, 6)))
    cut = short[:-6] + bytes([crc8(short[12:-6])])  # one item id short, CRC made good
    with pytest.raises(Exception) as exc:
        decode(cut)
    assert getattr(exc.value, "counter", "") == "malformed"


# --- RMAP ----------------------------------------------------------------------------------------


def test_rmap_write_command_layout_and_reply() -> None:
    w = rmap.Write(0xFE, 0x20, 0x1234, 0x00001000, b"\x01\x02\x03\x04")
    raw = rmap.encode_write(w)
    # target, pid, instruction (command, write, verify, reply, increment, 0 reply bytes), key,
    # initiator, transaction id, extended address, address, data length
    head = bytes([0xFE, 0x01, 0x7C, 0x00, 0x20, 0x12, 0x34, 0x00, 0, 0, 0x10, 0, 0, 0, 4])
    assert raw[:15] == head and raw[15] == crc8(head)
    assert raw[16:20] == b"\x01\x02\x03\x04" and raw[20] == crc8(b"\x01\x02\x03\x04")
    assert rmap.decode(raw) == w
    written = []
    target = rmap.Target(0xFE, lambda a, d: written.append((a, d)))
    reply = target.receive(raw)
    assert written == [(0x1000, b"\x01\x02\x03\x04")] and target.memory[0x1000] == b"\x01\x02\x03\x04"
    r = rmap.decode(reply)
    assert isinstance(r, rmap.WriteReply) and (r.initiator, r.target, r.transaction) == (0x20, 0xFE, 0x1234)
    assert r.status == rmap.Status.SUCCESS and reply[:4] == bytes([0x20, 0x01, 0x3C, 0x00])


def test_rmap_read_command_and_reply_layout_byte_by_byte() -> None:
    read = rmap.Read(0xFE, 0x42, 0x0109, 0x00000000, 8, reply_address=b"\x00\x00\x05\x01")
    raw = rmap.encode_read(read)
    # target, pid, instruction (command, read, reply, increment, one word of reply address), key,
    # reply address, initiator, transaction id, extended address, address, data length; no data
    head = bytes([0xFE, 0x01, 0x4D, 0x00, 0, 0, 5, 1, 0x42, 0x01, 0x09, 0x00, 0, 0, 0, 0, 0, 0, 8])
    assert raw == head + bytes([crc8(head)]) and rmap.decode(raw) == read
    data = b"R\x01\x03\x01\x00\x00\x00\x0e"
    reply = rmap.encode_read_reply(rmap.ReadReply(0x42, 0xFE, 0x0109, data))
    # initiator, pid, instruction (reply, read, increment), status, target, transaction id, reserved,
    # data length, header CRC, data, data CRC
    head = bytes([0x42, 0x01, 0x0C, 0x00, 0xFE, 0x01, 0x09, 0x00, 0, 0, 8])
    assert reply == head + bytes([crc8(head)]) + data + bytes([crc8(data)])
    assert rmap.decode(reply) == rmap.ReadReply(0x42, 0xFE, 0x0109, data)
    for bad in (raw + b"\x00", raw[:-1] + bytes([raw[-1] ^ 1]), reply[:-1], reply[:-1] + b"\x00"):
        with pytest.raises(rmap.RmapError):
            rmap.decode(bad)
    # a target of writes takes no read: dropped, counted
    target = rmap.Target(0xFE, lambda a, d: None)
    assert target.receive(raw) is None and target.counters.dropped == 1


def test_rmap_target_answers_bad_writes_with_a_status_and_drops_bad_headers() -> None:
    target = rmap.Target(0xFE, lambda a, d: None)
    raw = bytearray(rmap.encode_write(rmap.Write(0xFE, 0x20, 1, 0x10, b"abcd")))
    raw[-1] ^= 1  # data CRC
    assert rmap.decode(target.receive(bytes(raw))).status == rmap.Status.INVALID_DATA_CRC
    raw[3] ^= 1  # the key: header CRC now wrong
    assert target.receive(bytes(raw)) is None
    other = rmap.encode_write(rmap.Write(0x33, 0x20, 2, 0x10, b"abcd"))
    assert rmap.decode(target.receive(other)).status == rmap.Status.INVALID_TARGET
    assert target.receive(b"\x00\x01") is None and target.counters.dropped == 2
    assert target.memory == {}


def test_rmap_initiator_retries_after_its_fixed_timeout_then_gives_up() -> None:
    ini = rmap.Initiator(0x20, timeout_ns=200_000, retries=1)
    tid, raw = ini.write(0xFE, 0x1000, b"abcd", now=0)
    assert ini.expire(199_999) == ([], [])
    assert ini.expire(200_000) == ([raw], [])  # resent as it was
    assert ini.expire(400_000) == ([], [tid])
    assert ini.counters == rmap.InitiatorCounters(writes=1, retries=1, failed=1)
    tid2, raw2 = ini.write(0xFE, 0x1000, b"abcd", now=0)
    ack = rmap.Target(0xFE, lambda a, d: None).receive(raw2)
    assert ini.receive(ack) == (tid2, 0) and not ini.in_flight
    assert ini.receive(ack) is None and ini.counters.stray == 1  # a late duplicate ack


# --- SnP-TSP ---------------------------------------------------------------------------------------


def test_one_step_stamping_writes_the_departure_time_and_nothing_else() -> None:
    t = 0x1122334455667788
    for h in (Header(0, Pid.TSP, b"", 3, 4), Header(0xFE, Pid.TSP, b"\x05\x06", 3, 4)):  # (a return address)
        for made, sent in (
            (TimeRequest(1), TimeRequest(t)),
            (TimeResponse(1, 2, 3), TimeResponse(1, 2, t)),  # t3: when the response left
            (TimeBeacon(9, 3), TimeBeacon(9, t)),
        ):
            assert stamp_departure(encode(h, made), t) == encode(h, sent)  # CRC made anew too
    others = (
        encode(Header(0, Pid.TSP), TimeSubscribe(10_000_000, 20_000)),
        encode(Header(0, Pid.MRT), NodeInfoQuery()),
        encode(Header(0, Pid.TSP), TimeBeacon(1, 2))[:-3],  # cut short: left alone, not raised
        b"",
    )
    for other in others:
        assert stamp_departure(other, t) == other


def test_a_follow_up_names_the_beacon_or_response_and_carries_its_departure_byte_by_byte() -> None:
    t = 0x0102030405060708
    for h in (Header(0, Pid.TSP, b"", 3, 4), Header(0xFE, Pid.TSP, b"\x05\x06", 3, 4)):
        fu = follow_up(encode(h, TimeBeacon(0xAABBCCDD, 1)), t)
        assert fu == encode(h, TimeFollowUp(PacketType.TIME_BEACON, 0xAABBCCDD, t))  # to the same receiver
        data = fu[12 + len(h.return_address) :]
        assert data[:3] == bytes([0, 0x00, 0x15])  # reserved, TIME_FOLLOW_UP
        assert data[3:-1] == bytes([0, 0x14, 0, 0, 0, 0, 0xAA, 0xBB, 0xCC, 0xDD, 1, 2, 3, 4, 5, 6, 7, 8])
        assert data[-1] == crc8(data[:-1])
        got = decode(follow_up(encode(h, TimeResponse(77, 2, 3)), t) or b"").body
        assert got == TimeFollowUp(PacketType.TIME_RESPONSE, 77, t)  # a response: named by its t1
    for other in (
        encode(Header(0, Pid.TSP), TimeRequest(5)),  # (a request's departure is its sender's own)
        encode(Header(0, Pid.TSP), TimeSubscribe(10_000_000, 20_000)),
        encode(Header(0, Pid.MRT), NodeInfoQuery()),
        encode(Header(0, Pid.TSP), TimeBeacon(1, 2))[:-3],
        b"",
    ):
        assert follow_up(other, t) is None
    with pytest.raises(PacketError):  # cut short: refused, not raised as anything else
        decode(encode(Header(0, Pid.TSP), TimeFollowUp(PacketType.TIME_BEACON, 1, 2))[:-2])


def test_a_two_step_link_follows_time_packets_up_with_the_kernels_departure() -> None:
    import platform
    import socket
    import time

    from cell.snp.link import Link, drain, open_udp
    from cell.timer import realtime_offset

    a, b = open_udp(), open_udp(timestamps=True)
    told: list[tuple[bytes, int]] = []

    def departed(data: bytes, t: int) -> list[bytes]:
        told.append((data, t))
        fu = follow_up(data, t)
        return [fu] if fu else []

    try:
        link = Link(a, clock=lambda host_ns: host_ns, departed=departed)
        if not link.two_step:  # (SOF_TIMESTAMPING_OPT_RX_FILTER came with Linux 6.12)
            kernel = tuple(int(x) for x in platform.release().split("-")[0].split(".")[:2])
            assert kernel < (6, 12), f"Linux {platform.release()} should give transmit stamps"
            pytest.skip("this kernel gives no transmit stamps with a receive filter")
        info = encode(Header(0, Pid.MRT), NodeInfoQuery())
        before = time.monotonic_ns()
        link.send(encode(Header(0, Pid.TSP), TimeBeacon(3, 0)), b.getsockname())
        after = time.monotonic_ns()
        link.send(info, b.getsockname())
        with pytest.raises(BlockingIOError):  # nothing left queued to wake a polling loop
            a.recvmsg(0, 256, socket.MSG_ERRQUEUE)
        got = []
        deadline = time.monotonic() + 5
        while len(got) < 3 and time.monotonic() < deadline:
            got += drain(b, realtime_offset())
        (beacon, _, rx), (fu, _, _), (plain, _, _) = got
        one_step = decode(beacon).body.t_master
        precise = decode(fu).body
        assert precise == TimeFollowUp(PacketType.TIME_BEACON, 3, told[0][1]) and len(told) == 1
        assert before <= one_step <= precise.t <= after  # read before the send call; stamped in it
        assert 0 <= rx - precise.t < 1_000_000  # the receiver's kernel stamp comes right after it
        assert plain == info and link.sent == 3 and link.unstamped == 0
    finally:
        a.close()
        b.close()


def test_the_link_dates_time_packets_as_it_sends_them_and_leaves_the_rest() -> None:
    from cell.snp.link import Link, open_udp

    a, b = open_udp(), open_udp()
    b.settimeout(5.0)
    try:
        link = Link(a, clock=lambda host_ns: 42)  # (no departed: one-step only)
        info = encode(Header(0, Pid.MRT), NodeInfoQuery())
        link.send(encode(Header(0, Pid.TSP), TimeBeacon(1, 7)), b.getsockname())
        link.send(info, b.getsockname())
        assert decode(b.recv(2048)).body == TimeBeacon(1, 42)
        assert b.recv(2048) == info
        assert link.sent == 2
    finally:
        a.close()
        b.close()


def test_the_runner_samples_a_running_modules_clock_on_the_grid_it_is_given() -> None:
    from cell.snp.runner import Slot

    s = Slot(101, 0, 0, module=JointModule(101, 0), osc=Oscillator(0, 0.0, 0))
    assert s.module is not None
    s.sample(1_000_000, 10_000_000, (1_000_000, 400_000))
    assert s.clock_errors == []  # not running yet: nothing to sample
    s.module.state = ModuleState.RUNNING
    s.sample(1_234_567, 10_000_000, (1_000_000, 400_000))
    assert len(s.clock_errors) == 1 and s.next_sample == 11_400_000  # the slot after 10 ms
    s.sample(11_399_999, 10_000_000, (1_000_000, 400_000))
    assert len(s.clock_errors) == 1
    s.sample(11_400_000, 10_000_000)  # no grid: every 10 ms from the sample
    assert len(s.clock_errors) == 2 and s.next_sample == 21_400_000


def test_the_clock_servo_locks_to_beacons_despite_offset_drift_and_jitter() -> None:
    osc = Oscillator(offset_ns=1_700_000, drift_ppm=-45.0, true_origin=0)
    servo = ClockServo()
    delay, jitter = iter(itertools.cycle([30_000, 31_000, 45_000, 30_500])), 0
    t = 5_000_000
    servo.exchange(osc.raw(t), t + 30_000, t + 31_000, osc.raw(t + 61_000))  # a 61 us round trip
    errors = []
    for _k in range(300):  # 3 s of beacons every 10 ms
        t += 10_000_000
        d = next(delay)
        servo.beacon(osc.raw(t + d), t)  # left the master at t, came in after d
        errors.append(servo.now(osc.raw(t + d + 5_000_000)) - (t + d + 5_000_000))  # mid-period
        jitter = max(jitter, abs(d - 30_500))
    assert abs(errors[0]) > 200  # 45 ppm over 5 ms: the first step does not know the drift yet
    settled = [abs(e) for e in errors[100:]]
    assert max(settled) < jitter + 2_000, max(settled)  # within the path's jitter
    assert abs(servo.rate - 45e-6 / (1 - 45e-6)) < 2e-6  # it learnt the drift
    assert abs(servo.to_raw(servo.now(osc.raw(t))) - osc.raw(t)) <= 1


def test_a_module_takes_the_follow_ups_time_and_goes_back_to_one_step_when_they_stop() -> None:
    """The master's one-step stamps are read 20 us before its packets really leave (as a send call
    in Python takes here); its follow-ups carry when they did."""
    osc, early, path = Oscillator(offset_ns=900_000, drift_ppm=30.0, true_origin=0), 20_000, 500
    m = JointModule(11, 0)
    h = Header(0, Pid.TSP)
    m.receive(encode(Header(0, Pid.MRT), Configure(0, 1_000_000, 0, 1_000_000, (20.0,))), 0)
    t = 1_000_000
    for _ in range(8):  # the two-way exchanges: the request leaves at t (its kernel: t + 3 us)
        m.departed(encode(h, TimeRequest(osc.raw(t))), osc.raw(t + 3_000))
        t2, t3 = t + 3_000 + path, t + 50_000  # the master's: arrived, and really left
        response = encode(h, TimeResponse(osc.raw(t), t2, t3 - early))
        m.receive(response, osc.raw(t3 + path))
        m.receive(follow_up(response, t3) or b"", osc.raw(t3 + path + 1_000))
        t += 200_000
    assert m.two_step and abs(m.servo.delay_ns - path) < 5  # the path, not the early stamps' 10 us more

    def beacons(n: int, followed: bool) -> int:
        nonlocal t
        for seq in range(n):
            t += 10_000_000
            beacon = encode(h, TimeBeacon(seq, t - early))
            m.receive(beacon, osc.raw(t + path))
            if followed:
                m.receive(follow_up(beacon, t) or b"", osc.raw(t + path + 2_000))
        return m.servo.now(osc.raw(t + 5_000_000)) - (t + 5_000_000)  # the clock's error, mid-period

    assert abs(beacons(40, followed=True)) < 100  # ns: the follow-ups' times
    # (the first response went one-step: its follow-up is how the module learns there are any)
    assert m.state == ModuleState.RUNNING and m.follow_ups == 7 + 40 and m.unfollowed == 0
    samples = m.servo.samples
    beacons(3, followed=False)  # waiting for their follow-ups (the last one's may still come)
    assert m.two_step and m.servo.samples == samples and m.unfollowed == 2
    # the next beacon makes three missed in a row: the master stopped them; one-step from it on
    assert abs(beacons(40, followed=False) + early) < 1_000  # 20 us behind, as the stamps say
    assert not m.two_step and m.unfollowed == 3 and m.servo.samples == samples + 40


def test_a_module_asks_again_when_a_time_exchange_is_lost_within_its_eight() -> None:
    m = JointModule(11, 0)
    h = Header(0, Pid.TSP)
    sent = m.receive(encode(Header(0, Pid.MRT), Configure(0, 1_000_000, 0, 1_000_000, (20.0,))), 0)
    requests = [decode(d).body for d in sent if isinstance(decode(d).body, TimeRequest)]
    t = 0

    def beacon() -> list[TimeRequest]:
        nonlocal t
        t += 10_000_000
        return [decode(d).body for d in m.receive(encode(h, TimeBeacon(t, t)), t)]

    assert len(requests) == 1 and beacon() == []  # one beacon later: its answer may still come
    again = beacon()  # two: lost on the way; asked again
    assert len(again) == 1 and isinstance(again[0], TimeRequest)
    # answered, and its follow-up: the next one
    response = encode(h, TimeResponse(again[0].t1, t, t + 1_000))
    assert [type(decode(d).body) for d in m.receive(response, t + 2_000)] == [TimeRequest]
    follow = encode(h, TimeFollowUp(PacketType.TIME_RESPONSE, again[0].t1, t + 1_500))
    assert m.receive(follow, t + 2_100) == [] and m.two_step  # (the module learns of two-step)
    # a response whose follow-up is lost is dropped after two beacons too (not taken one-step)
    m.receive(encode(h, TimeResponse(again[0].t1 + 1, t, t + 1_000)), t + 2_000)
    asked = [r for _ in range(40) for r in beacon()]
    # (no follow-ups: one-step again after three; the first two beacons came before two-step)
    assert not m.two_step and m.servo.samples == 2 + 40 - 3
    assert 1 + 1 + 1 + len(asked) == 8  # eight requests in all, however many are lost
    late = encode(h, TimeFollowUp(PacketType.TIME_RESPONSE, again[0].t1 + 1, t))
    assert m.receive(late, t) == []  # the dropped exchange's follow-up, too late: nothing


def test_the_master_grants_beacon_periods_and_sends_what_is_due() -> None:
    b = BeaconSchedule()
    assert b.subscribe("a", 100_000, now=0) == MIN_PERIOD_NS  # faster than it offers: its fastest
    assert b.subscribe("b", 10_000_000, now=0) == 10_000_000
    assert sorted(b.due(0)) == [("a", 1), ("b", 1)]
    assert b.due(500_000) == []
    assert b.due(1_000_000) == [("a", 2)]
    assert b.due(10_500_000) == [("a", 3), ("b", 2)]  # a late call: one beacon, not a burst
    b.subscribe("a", 0, now=0)
    assert len(b) == 1


def test_beacons_on_a_grid_leave_in_its_slot_in_whole_periods_spread_over_them() -> None:
    b = BeaconSchedule(grid=(1_000_000, 400_000))  # the management slot: 0.4 ms into each 1 ms
    assert b.subscribe("c", 2_500_000, now=0) == 3_000_000  # whole grid periods
    for i in range(10):  # ten modules asking for 10 ms beacons at about the same time
        assert b.subscribe(f"m{i}", 10_000_000, now=123_456 + 7_000 * i) == 10_000_000
    sent: dict[int, list[object]] = {}  # grid period -> beacons sent in it
    for now in range(0, 100_000_000, 10_000):
        for addr, _seq in b.due(now):
            assert now % 1_000_000 == 400_000  # in the slot, never elsewhere
            sent.setdefault(now // 1_000_000, []).append(addr)
    per_module = {a: sum(v.count(a) for v in sent.values()) for a in (f"m{i}" for i in range(10))}
    assert set(per_module.values()) == {10}  # each its 10 ms period
    # one module's beacon a period: the ten take the ten periods of their 10 ms
    assert max(sum(a != "c" for a in v) for v in sent.values()) == 1
    b.subscribe("m0", 10_000_000, now=50_000_000)  # asked again: moved, not doubled
    assert len(b) == 11


# --- the modular robot on simulated time -----------------------------------------------------------


class SimNet:
    """A master and modules exchanging datagrams through a queue, each delivered after `latency`."""

    def __init__(self, ports: int, latency: int = 40_000, config: CycleConfig | None = None) -> None:
        self.now = 0
        self.latency = latency
        self.master = Master([("port", i) for i in range(ports)], config or CycleConfig(), lambda: self.now)
        self.modules: dict[int, tuple[JointModule, Oscillator]] = {}
        self.queue: list[tuple[int, int, str, object, bytes]] = []
        self.seq = itertools.count()
        self.sent: list[tuple[int, str, bytes]] = []  # (when, "master" or "module", datagram)
        self.drop: Callable[[str, bytes], bool] = lambda to, data: False  # lost on the way

    def plug(self, port: int, module_id: int, parent: int, transport: str = "snp") -> JointModule:
        m = JointModule(module_id, parent, 1)
        m.use_transport(transport)
        self.modules[port] = (m, Oscillator(300_000 * (port + 1), 20.0 * (port - 1), 0))
        return m

    def unplug(self, port: int) -> None:
        del self.modules[port]

    def _send(self, to: str, addr: object, data: bytes) -> None:
        self.sent.append((self.now, to, data))
        if self.drop(to, data):
            return
        heapq.heappush(self.queue, (self.now + self.latency, next(self.seq), to, addr, data))

    def run_until(self, t_end: int, step: int = 50_000) -> None:
        while self.now < t_end:
            self.now += step
            while self.queue and self.queue[0][0] <= self.now:
                _, _, to, addr, data = heapq.heappop(self.queue)
                if to == "master":
                    for d, a in self.master.receive(data, addr):
                        self._send("module", a, d)
                elif addr[1] in self.modules:  # (a datagram to an empty port is lost)
                    m, osc = self.modules[addr[1]]
                    for d in m.receive(data, osc.raw(self.now)):
                        self._send("master", addr, d)
            for d, a in (*self.master.serve(), *self.master.poll(), *self.master.beacons()):
                self._send("module", a, d)
            for port, (m, osc) in list(self.modules.items()):
                for d in m.poll(osc.raw(self.now)):
                    self._send("master", ("port", port), d)


def test_the_master_explores_configures_by_topology_and_runs_the_cycle() -> None:
    net = SimNet(ports=4)
    # plugged in any order of ports: the chain is base plate <- 11 <- 12 <- 13
    m13, m11, m12 = net.plug(0, 13, 12), net.plug(2, 11, 0), net.plug(3, 12, 11)
    net.run_until(300_000_000)
    assert (m11.joint, m12.joint, m13.joint) == (0, 1, 2)
    assert [n.state for n in net.master.nodes.values()] == ["included"] * 3
    assert all(m.state == ModuleState.RUNNING and m.granted is not None for m in (m11, m12, m13))
    for m in (m11, m12, m13):
        assert len(m.cycles) > 150 and m.missed == {"ab": 0, "cd": 0}
        start, _t1, end, missed = m.cycles[-1]
        assert 0 <= end - start < 500_000  # two round trips of 40 us, and the servo's error
        assert missed == 0
    assert net.master.counters.guessed == 0
    assert abs(m13.servo.now(net.modules[0][1].raw(net.now)) - net.now) < 5_000  # clock locked


def test_a_time_slotted_schedule_starts_each_joint_in_its_slot_and_fdir_follows_it() -> None:
    net = SimNet(ports=3, latency=20_000, config=CycleConfig(slot_ns=150_000))
    mods = [net.plug(0, 11, 0), net.plug(1, 12, 11), net.plug(2, 13, 12)]
    net.run_until(300_000_000)
    for m in mods:
        assert m.config is not None and m.config.phase_ns == 150_000 * m.joint
        assert len(m.cycles) > 150 and m.missed == {"ab": 0, "cd": 0}
        scheduled = [c[0] for c in m.cycles[-50:]]
        assert {t % 1_000_000 for t in scheduled} == {150_000 * m.joint}  # on its slot of the grid
    assert net.master.counters.guessed == 0  # each joint's A checked against its own slot
    net.unplug(2)
    t_pull = net.now
    net.run_until(t_pull + 10_000_000)
    silent = [t - t_pull for t, what, mid, _ in net.master.events if what == "silent" and mid == 13]
    assert silent and 2_000_000 <= silent[0] <= 5_000_000


def test_a_module_plugged_in_while_running_is_included_one_pulled_out_is_guessed_then_dropped() -> None:
    net = SimNet(ports=3)
    net.plug(0, 11, 0)
    net.plug(1, 12, 11)
    net.run_until(200_000_000)
    late = net.plug(2, 13, 12)
    t_plug = net.now
    net.run_until(t_plug + 150_000_000)
    assert late.state == "running" and late.joint == 2 and late.cycles
    included = [t for t, what, mid, _ in net.master.events if what == "included" and mid == 13]
    assert included and included[0] - t_plug < 60_000_000  # the next exploration round, then configured
    net.unplug(1)
    t_pull = net.now
    net.run_until(t_pull + 100_000_000)
    events = {what: t - t_pull for t, what, mid, _ in net.master.events if mid == 12 and t >= t_pull}
    assert 2_000_000 <= events["silent"] <= 5_000_000  # 3 cycles without its A
    assert 50_000_000 <= events["lost"] <= 52_000_000
    assert net.master.counters.guessed >= 3
    others = [net.modules[0][0], late]
    assert all(m.missed == {"ab": 0, "cd": 0} for m in others)  # the cycle went on, 12 guessed
    assert not net.master.model.active[1]
    back = net.plug(1, 12, 11)  # plugged back: found and configured again, as joint 1
    net.run_until(net.now + 150_000_000)
    assert back.state == "running" and back.joint == 1 and back.cycles
    assert [w for _, w, mid, _ in net.master.events if mid == 12][-2:] == ["found", "included"]


def test_a_module_whose_subscription_was_lost_subscribes_again_when_configured_again() -> None:
    net = SimNet(ports=2)
    lost: list[bytes] = []

    def first_subscription(to: str, data: bytes) -> bool:
        if to == "master" and not lost and isinstance(decode(data).body, TimeSubscribe):
            lost.append(data)
            return True
        return False

    net.drop = first_subscription
    m11, m12 = net.plug(0, 11, 0), net.plug(1, 12, 11)
    net.run_until(400_000_000)
    assert lost  # one module's TIME_SUBSCRIBE was lost: no beacons, it could not sync
    events = [(w, mid) for _, w, mid, _ in net.master.events]
    unlucky = next(mid for w, mid in events if w == "lost")  # silent 50 ms: excluded
    assert ("included", unlucky) in events[events.index(("lost", unlucky)) :]  # found, configured
    assert m11.state == m12.state == "running" and m11.cycles and m12.cycles  # it subscribed again,
    assert len(net.master.beacon_schedule) == 2  # synced and runs


def test_the_master_sends_beacons_and_probes_only_in_its_management_slot() -> None:
    config = CycleConfig(slot_ns=100_000, management_ns=450_000)
    net = SimNet(ports=4, latency=20_000, config=config)
    mods = [net.plug(0, 11, 0), net.plug(1, 12, 11), net.plug(2, 13, 12)]
    net.run_until(300_000_000)
    assert all(m.state == ModuleState.RUNNING for m in mods)
    kinds: dict[type, list[int]] = {}
    for t, to, data in net.sent:
        body = decode(data).body if to == "module" else None
        if t > 50_000_000 and isinstance(body, TimeBeacon | NodeInfoQuery):  # (after start-up)
            kinds.setdefault(type(body), []).append(t)
    assert len(kinds[TimeBeacon]) > 3 * 20 and len(kinds[NodeInfoQuery]) > 10  # (the free port's)
    for times in kinds.values():  # within the step after the slot opens
        assert {(t - 450_000) % 1_000_000 < 50_000 for t in times} == {True}
    periods = [t // 1_000_000 for t in kinds[TimeBeacon]]
    assert len(set(periods)) == len(periods)  # no two modules' beacons in one period
    for m in mods:  # and the cycle itself is untouched
        assert m.missed == {"ab": 0, "cd": 0} and net.master.counters.guessed == 0


def test_junk_reaches_master_and_module_without_harm() -> None:
    net = SimNet(ports=1)
    m = net.plug(0, 11, 0)
    net.run_until(100_000_000)
    before = len(m.cycles)
    junk = [
        b"",
        b"\x00",
        b"\x00\x01",
        b"\x00\x01\x40",
        bytes(7) + b"\x01",
        b"\xfe\x01" + bytes(30),
        bytes(40),
        # follow-ups of beacons and responses never sent, and one cut short: the module (whose master
        # here stamps one-step) waits for follow-ups that do not come, then goes back to one-step
        encode(Header(0, Pid.TSP), TimeFollowUp(PacketType.TIME_BEACON, 999, 5)),
        encode(Header(0, Pid.TSP), TimeFollowUp(PacketType.TIME_RESPONSE, 7, 5)),
        encode(Header(0, Pid.TSP), TimeFollowUp(0x0999, 7, 5)),
        encode(Header(0, Pid.TSP), TimeFollowUp(PacketType.TIME_BEACON, 1, 2))[:-4],
    ]
    for j in junk:
        assert isinstance(net.master.receive(j, ("port", 0)), list)
        assert isinstance(m.receive(j, 0), list)
    samples = m.servo.samples
    net.run_until(net.now + 100_000_000)
    assert len(m.cycles) > before and m.state == ModuleState.RUNNING  # nothing a peer sends stops either end
    assert not m.two_step and m.servo.samples >= samples + 5  # its clock still servoed


def test_the_rmap_baseline_runs_the_same_cycle_with_acknowledged_writes() -> None:
    net = SimNet(ports=2)
    m1, m2 = net.plug(0, 11, 0, "rmap"), net.plug(1, 12, 11, "rmap")
    net.run_until(300_000_000)
    for m in (m1, m2):
        assert m.state == ModuleState.RUNNING and len(m.cycles) > 150 and m.missed == {"ab": 0, "cd": 0}
        _start, t1, end, missed = m.cycles[-1]
        assert end - t1 >= 4 * net.latency  # A, then B (with A's ack), C, then D (with C's ack)
        assert missed == 0
        assert m.rmap_init is not None and m.rmap_init.counters.acked >= 2 * len(m.cycles) - 2
        assert m.rmap_target.counters.replies >= 2 * len(m.cycles) - 2  # it acked B and D
    # eight packets a cycle (a write and its ack per message) against the queries' four
    assert net.master.rmap_init.counters.acked >= 2 * (len(m1.cycles) + len(m2.cycles)) - 4
    assert net.master.rmap_target.counters.replies >= 2 * (len(m1.cycles) + len(m2.cycles)) - 4


def test_the_masters_fast_path_answers_as_its_full_handler_does() -> None:
    """The cycle's A and C, parsed by their shapes, get the answers (and denials) the full decoder
    and handler give the same queries (sent with a return address byte: not a fast shape)."""
    from cell.snp.modular import FORCE, TORQUE, item
    from cell.snp.packet import Denied, Item, Quantity, Query, Reply, Wanted

    net = SimNet(ports=2)
    net.plug(0, 11, 0)
    net.plug(1, 12, 11)
    net.run_until(100_000_000)
    master, t = net.master, net.now
    state = (Item(item(Quantity.POSITION, 1), 0.25, t), Item(item(Quantity.VELOCITY, 1), 0.5, t))
    a = Query(7, t + 500_000, state, (Wanted(item(Quantity.COMMANDED_VELOCITY, 1), t + 1_000_000),))
    c = Query(8, t + 900_000, (Item(item(FORCE, 1), 1.5, t),), (Wanted(item(TORQUE, 1), t + 1_000_000),))
    late = Query(9, t - 1, a.inputs, a.outputs)  # its deadline passed: denied
    answers = {}
    for rab in (b"", b"\x07"):  # the fast path, then the full one
        h = Header(0, Pid.MRT, rab, 99, 0)
        got = []
        for q in (a, c, late):
            out = master.receive(encode(h, q), ("port", 1)) + master.serve()
            assert len(out) == 1 and out[0][1] == ("port", 1)
            got.append(decode(out[0][0]))
        answers[rab] = got
    fast, full = answers[b""], answers[b"\x07"]
    for f, g in zip(fast, full, strict=True):
        assert f.body == g.body and f.header.destination_process == 99
    assert isinstance(fast[0].body, Reply) and fast[0].body.items[0].id == item(
        Quantity.COMMANDED_VELOCITY, 1
    )
    assert isinstance(fast[1].body, Reply) and fast[1].body.items[0].id == item(TORQUE, 1)
    assert isinstance(fast[2].body, Denied)
    assert master.model.pos[1] == 0.25 and master.model.force[1] == 1.5  # the inputs taken either way


def test_a_query_queued_by_the_fast_path_can_be_cancelled() -> None:
    from cell.snp.modular import item
    from cell.snp.packet import Cancel, Denial, Denied, Item, Quantity, Query, Wanted

    net = SimNet(ports=1)
    net.plug(0, 11, 0)
    net.run_until(100_000_000)
    master, t = net.master, net.now
    h = Header(0, Pid.MRT, b"", 5, 0)
    state = (Item(item(Quantity.POSITION, 0), 0.1, t), Item(item(Quantity.VELOCITY, 0), 0.0, t))
    q = Query(3, t + 500_000, state, (Wanted(item(Quantity.COMMANDED_VELOCITY, 0), t + 1_000_000),))
    assert master.receive(encode(h, q), ("port", 0)) == [] and master.handler.pending == 1
    (out,) = master.receive(encode(h, Cancel(3)), ("port", 0))
    assert decode(out[0]).body == Denied(3, Denial.CANCELLED)
    assert master.serve() == [] and master.handler.pending == 0


# --- on real UDP sockets ---------------------------------------------------------------------------


def test_master_and_modules_on_loopback_sockets() -> None:
    from cell.snp.runner import Slot, run_modules

    with snp_master_on_loopback(2) as (master, ports):
        slots = [
            Slot(21, 0, ports[0], offset_ns=1_000_000, drift_ppm=30.0),
            Slot(22, 21, ports[1], offset_ns=-800_000, drift_ppm=-30.0),
        ]
        run_modules(slots, seconds=1.5, spin=False)
    for s in slots:
        m = s.module
        assert m is not None and m.state == ModuleState.RUNNING and m.joint == s.module_id - 21
        assert len(m.cycles) > 500  # on this 2-core machine, in one process with the master
        in_cycles = sum(c[3] for c in m.cycles)  # each cycle's guesses, as counted per module
        assert sum(m.missed.values()) - 1 <= in_cycles <= sum(m.missed.values())  # (one may be running)
        assert s.clock_errors and abs(s.clock_errors[-1]) < 1_000_000  # servoed (it started 1 ms off)
    assert master.counters.included == 2
    h = master.handler.counters  # (how many make their deadline depends on the machine's load)
    denied = sum(h.denied.values())
    assert h.queries > 1000 and h.replies > 0 and h.replies + denied == h.queries
