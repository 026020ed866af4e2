"""The Responsive Link's cell parts without a cell: event payloads byte by byte, stations and their
watchdog, the data plane's stop stage and packet-out, halted drives, the hub's host interface."""

from __future__ import annotations

import asyncio
import socket
import time

import numpy as np
import pytest

from cell.config import load_config
from cell.ports import free_block, free_port
from cell.rlink import events
from cell.rlink.cellnet import BROADCAST, PORTS, Topology
from cell.rlink.client import EventClient
from cell.rlink.events import ALL, EventError, Reason, RobotSet, RobotState, StateReport
from cell.rlink.packet import EventType, Kind, Packet
from cell.rlink.station import Station
from cell.robot import datagram, udp
from cell.robot.datagram import SCALE
from cell.robot.drive import HOLD_UR, Drives

# --- payloads ------------------------------------------------------------------------------------


def test_robot_sets_are_token_base_mask_in_network_order() -> None:
    (rs,) = events.robot_sets([3, 5], token=0xBEEF)
    assert rs.encode() == bytes.fromhex("beef 0003 00000005")  # bits 0 and 2: robots 3 and 5
    assert events.decode_set(rs.encode()) == rs
    assert rs.ids({1, 2, 3, 4, 5, 6}) == [3, 5] and rs.ids({5}) == [5]
    (every,) = events.robot_sets(None, token=1)
    assert every.encode() == bytes.fromhex("0001 ffff 00000000") and every.ids({7, 9}) == [7, 9]


def test_robots_further_apart_than_32_take_several_sets() -> None:
    sets = events.robot_sets([1, 2, 40, 300], token=9)
    assert [(s.base, s.mask) for s in sets] == [(1, 0b11), (40, 1), (300, 1)]
    named = sorted(r for s in sets for r in s.ids(set(range(1000))))
    assert named == [1, 2, 40, 300]


@pytest.mark.parametrize(
    "payload",
    [b"", b"\x00" * 7, b"\x00" * 9, bytes.fromhex("0001 0005 00000000")],  # last: names nobody
)
def test_bad_robot_sets_are_refused(payload: bytes) -> None:
    with pytest.raises(EventError):
        events.decode_set(payload)


def test_state_reports_and_beacons_round_trip_byte_by_byte() -> None:
    rep = StateReport(258, RobotState.STILL, Reason.ESTOP, 1234)
    assert rep.encode() == bytes.fromhex("0102 02 01 000004d2")
    assert events.decode_state(rep.encode()) == rep
    with pytest.raises(EventError):
        events.decode_state(bytes.fromhex("0102 09 01 00000000"))  # no state 9
    assert events.encode_beacon(0x0102030405060708) == bytes(range(1, 9))
    assert events.decode_beacon(bytes(range(1, 9))) == 0x0102030405060708


# --- stations ------------------------------------------------------------------------------------


def _event(type: EventType, payload: bytes, src: int = 1) -> Packet:
    return Packet(Kind.EVENT, BROADCAST, src, 3, type, 0, payload)


def test_a_station_orders_stops_and_resumes_for_its_own_robots_only() -> None:
    st = Station({1, 2})
    order = st.on_event(_event(EventType.ESTOP, events.robot_sets([2, 7], 5)[0].encode()), 0)
    assert order is not None and order.stop and order.emergency and order.robots == [2]
    assert order.token == 5 and st.stopped == {2: Reason.ESTOP}
    assert st.on_event(_event(EventType.STOP, events.robot_sets([7], 5)[0].encode()), 0) is None  # not ours
    st.on_event(_event(EventType.STOP, events.robot_sets([2], 6)[0].encode()), 0)
    assert st.stopped[2] == Reason.ESTOP  # a stop does not weaken an e-stop
    order = st.on_event(_event(EventType.RESUME, events.robot_sets(None, 7)[0].encode()), 0)
    assert order is not None and not order.stop and order.robots == [1, 2] and st.stopped == {}
    assert st.on_event(_event(EventType.ESTOP, b"\x01"), 0) is None and st.counters.bad_events == 1


def test_the_watchdog_stops_on_silence_and_the_beacon_resumes_only_what_it_stopped() -> None:
    ms = 1_000_000
    st = Station({1, 2}, watchdog_ns=100 * ms)
    assert st.check(10_000 * ms) is None  # not armed before the first beacon
    st.on_event(_event(EventType.BEACON, events.encode_beacon(5)), 0)
    st.on_event(_event(EventType.ESTOP, events.robot_sets([1], 1)[0].encode()), 10 * ms)
    assert st.check(99 * ms) is None
    order = st.check(100 * ms)
    assert order is not None and order.stop and order.robots == [2] and order.reason == Reason.WATCHDOG
    assert st.check(500 * ms) is None and st.counters.watchdog_trips == 1  # tripped once, not per check
    back = st.on_event(_event(EventType.BEACON, events.encode_beacon(6)), 600 * ms)
    assert back is not None and not back.stop and back.robots == [2]
    assert st.stopped == {1: Reason.ESTOP}  # the e-stop holds until a resume names it


# --- drives ----------------------------------------------------------------------------------------


def test_halted_drives_brake_at_full_deceleration_and_ignore_commands_until_released() -> None:
    d = Drives(2, v_max=np.full(6, 3.0), a_max=np.full(6, 5.0))
    d.command(np.zeros(6, np.int64), np.arange(6), np.full(6, 1.0))
    d.command(np.ones(6, np.int64), np.arange(6), np.full(6, 1.0))
    d.end_window()
    for _ in range(200):
        d.step(0.002)
    assert np.allclose(d.velocity, 1.0)
    d.halt(np.array([0]))
    d.command(np.zeros(6, np.int64), np.arange(6), np.full(6, 2.0))  # ignored while halted
    d.end_window()
    steps = 0
    while d.velocity[0].any():
        d.step(0.002)
        steps += 1
    assert steps == 100  # 1 rad/s at 5 rad/s^2: 0.2 s
    assert np.allclose(d.velocity[1], 1.0)  # the other robot goes on
    d.halt(np.array([0]), on=False)
    d.command(np.zeros(6, np.int64), np.arange(6), np.full(6, 0.5))
    d.end_window()
    d.step(0.002)
    assert d.velocity[0, 0] > 0


def test_an_estop_hold_outlasts_another_holders_release() -> None:
    """A UR dashboard's brake release (cell.ur) does not let go of a robot the e-stop holds."""
    d = Drives(1, v_max=np.full(6, 3.0), a_max=np.full(6, 5.0))
    row = np.array([0])
    d.halt(row)  # the e-stop
    d.halt(row, by=HOLD_UR)  # powered off on the dashboard
    d.halt(row, on=False, by=HOLD_UR)  # brake release
    d.command(np.zeros(6, np.int64), np.arange(6), np.full(6, 1.0))
    d.end_window()
    d.step(0.002)
    assert d.halted[0] and not d.velocity.any()  # still held by the e-stop, deaf to commands
    d.halt(row, on=False)  # the e-stop's resume
    d.command(np.zeros(6, np.int64), np.arange(6), np.full(6, 1.0))
    d.end_window()
    d.step(0.002)
    assert not d.halted[0] and d.velocity[0, 0] > 0


# --- the data plane ----------------------------------------------------------------------------------


@pytest.fixture
def plane():
    from cell.dataplane.plane import DataPlane
    from cell.dataplane.tables import TP

    rob = [{"id": r, "name": f"b{r}", "skill_port": 20000 + r} for r in (1, 2, 3)]
    cfg = load_config(
        overrides={
            "robots": rob,
            "dataplane": {"listen": f"127.0.0.1:{free_port(socket.SOCK_DGRAM)}"},
            "rlink": {"port": free_block(PORTS)},
        }
    )
    p = DataPlane(cfg)
    p.tables.insert([TP(r, 1, 1, 1.0, [1.0] * 6, [0.5] * 6) for r in (1, 2, 3)])
    for r in (1, 2, 3):
        p.tables.set_registers(r, 1, 2**62)
    yield p
    p.close()


def _status(robot: int, v: float) -> np.ndarray:
    recs = datagram.empty(6)
    recs["robot_id"], recs["joint_id"], recs["velocity"] = robot, np.arange(6), round(v * SCALE)
    return recs


def test_a_stop_sends_ramp_commands_at_once_and_holds_every_command_after(plane) -> None:
    robot = udp.open_socket("127.0.0.1", gro=False)
    udp.Sender(robot, datagram.SIZE).send(memoryview(_status(2, 1.0).tobytes()), plane.sock.getsockname())
    deadline = time.monotonic() + 2
    while plane.handle() == 0:
        assert time.monotonic() < deadline
    robot.settimeout(2)
    before = [datagram.view(bytearray(robot.recv(64))) for _ in range(6)]
    assert all(
        b["velocity"][0] > 1.0 * SCALE for b in before
    )  # following its TP (0.5 rad/s + the position error)
    window = 1 / 125
    ramp = 1.0 - 5.0 * 0.95 * window  # the arm's deceleration x stop_decel over one window
    assert plane.stop_robots([2]) == 6  # a command per joint, now, without waiting for a status
    got = [datagram.view(bytearray(robot.recv(64))) for _ in range(6)]
    assert all(g["robot_id"][0] == 2 and g["kind"][0] == datagram.Kind.COMMAND for g in got)
    assert np.allclose([g["velocity"][0] / SCALE for g in got], ramp, atol=1e-6)
    assert plane.tables.current_tp(2) is None  # the trajectory is let go
    # its next status is answered with the ramp again; the other robots still follow their TPs
    recs = np.concatenate([_status(1, 1.0), _status(2, 0.5)])
    plane.pipeline.process(recs, time.monotonic_ns())
    assert np.allclose(recs["velocity"][6:] / SCALE, 0.5 - 5.0 * 0.95 * window, atol=1e-6)
    assert (recs["velocity"][:6] > 1.0 * SCALE).all()
    tiny = _status(2, 0.001)
    plane.pipeline.process(tiny, time.monotonic_ns())
    assert (tiny["velocity"] == 0).all()  # never past 0
    plane.resume_robots([2])
    held = _status(2, 0.3)
    plane.pipeline.process(held, time.monotonic_ns())
    assert (held["velocity"] == 0).all()  # resumed: holds (no trajectory) until the controller loads
    robot.close()


async def test_register_updates_of_a_stopped_robot_are_refused(plane) -> None:
    from cell.bus import RpcFault
    from cell.v1 import dataplane_pb2

    plane.stop_robots([3])
    req = dataplane_pb2.TableUpdate(
        registers=[dataplane_pb2.RegisterEntry(robot_id=3, tp_id=1, next_time_ns=1)]
    )
    with pytest.raises(RpcFault) as err:
        await plane.update(req)
    assert err.value.code == "stopped"
    plane.resume_robots([3])
    await plane.update(req)
    assert plane.tables.current_tp(3) == 1


def test_a_stop_that_comes_in_mid_batch_holds_for_the_whole_batch(plane) -> None:
    """Slices processed before the stop are turned into stop commands too, before anything is sent."""
    from cell.dataplane import plane as svc

    sender_sock = udp.open_socket("127.0.0.1")
    n = svc.SLICE * 2 // 6 + 1  # statuses of robot 1 over three slices
    recs = np.concatenate([_status(1, 1.0)] * n)
    raw, out = memoryview(recs.tobytes()), udp.Sender(sender_sock, datagram.SIZE)
    for i in range(0, len(raw), 60 * datagram.SIZE):  # (GSO takes 64 datagrams a call at most)
        out.send(raw[i : i + 60 * datagram.SIZE], plane.sock.getsockname())
    calls = []

    def poll() -> None:  # the event comes in after the first slice
        if not calls:
            plane.stop_robots([1])
        calls.append(1)

    plane.poll = poll
    deadline = time.monotonic() + 2
    handled = 0
    while handled < recs.size:
        handled += plane.handle()
        assert time.monotonic() < deadline
    assert calls, "the batch was not sliced"
    got: list[np.ndarray] = []
    while sum(g.size for g in got) < recs.size:
        batch = udp.recv_batch(sender_sock)
        if batch is not None:
            got.append(datagram.view(bytearray(batch[0])))
        assert time.monotonic() < deadline + 2
    cmds = np.concatenate(got)
    assert cmds.size == recs.size and (cmds["velocity"] < 1.0 * SCALE).all()  # every one a ramp
    sender_sock.close()


# --- the hub's host interface ---------------------------------------------------------------------------


async def test_clients_of_the_host_interface_reach_the_nodes_and_hear_their_reports() -> None:
    from cell.rlink.hub import Hub
    from cell.rlink.link import NodeLink
    from cell.rlink.node import Node

    cfg = load_config(overrides={"rlink": {"port": free_block(PORTS), "beacon_hz": 0.0}})
    topo = Topology(cfg.rlink)
    hub = Hub(cfg)
    seen: list[Packet] = []

    def robots_node(p: Packet) -> None:  # plays the robots' node: a report for every order
        seen.append(p)
        if p.type == EventType.ESTOP:
            for rid in events.decode_set(p.payload).ids({1, 2}):
                rep = StateReport(rid, RobotState.STILL, Reason.ESTOP, 10).encode()
                leaf.send(Kind.EVENT, topo.address("hub"), EventType.STATE, rep, priority=2)

    leaf = NodeLink(Node(topo.address("robots"), topo.table("robots")), topo.links("robots"), robots_node)
    async with asyncio.TaskGroup() as tg:
        tasks = [tg.create_task(hub.link.run()), tg.create_task(leaf.run())]
        async with EventClient(cfg) as one, EventClient(cfg) as other:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as junk:  # counted, dropped, harmless
                for raw in (b"", b"\x00" * 15, b"\xff" * 16, b"\x00" * 4000):
                    junk.sendto(raw, topo.host)
            took = await one.estop(["r1"])
            assert set(took) == {1} and took[1] < 1000
            async with asyncio.timeout(2):
                while not any(r.robot == 1 for r in other.reports):  # every client hears every report
                    await asyncio.sleep(0.01)
            with pytest.raises(TimeoutError, match=r"\[2\] did not report resumed"):
                await one.resume(["r2"], timeout=0.3)  # nobody answers resumes here
            with pytest.raises(KeyError):
                await one.estop(["ghost"])
        for t in tasks:
            t.cancel()
    assert [p.type for p in seen] == [EventType.ESTOP, EventType.RESUME]
    assert hub.link.node.drops["no_route"] == 0 and hub.counters.reports == 1
    drops = hub.link.node.drops
    assert drops["truncated"] == 2 and drops["crc"] == 1 and drops["oversized"] == 1, drops
    hub.close()
    leaf.close()


def test_every_node_routes_to_every_other_and_broadcasts_reach_all() -> None:
    topo = Topology(load_config().rlink)
    hub, dp, rb = (topo.address(r) for r in ("hub", "dataplane", "robots"))
    t = {r: topo.table(r) for r in ("hub", "dataplane", "robots")}
    assert t["hub"].lookup(Kind.EVENT, hub, dp, 3)[0] == 0b00010  # L1
    assert t["hub"].lookup(Kind.EVENT, hub, rb, 3)[0] == 0b00100  # L2
    assert t["hub"].lookup(Kind.EVENT, hub, BROADCAST, 3)[0] == 0b00111  # host, L1, L2
    assert t["dataplane"].lookup(Kind.EVENT, hub, dp, 3)[0] == 0b00001
    assert t["robots"].lookup(Kind.EVENT, rb, hub, 2)[0] == 0b00010  # reports go up to the hub
    assert (
        len({p for r in ("hub", "dataplane", "robots") for lp in topo.links(r) for p in (lp.event, lp.data)})
        == 8
    )
    assert RobotSet(0, ALL, 0).ids({4}) == [4]
