"""The XDP backend against the numpy pipeline: the same tables and statuses, bit-identical commands.

The kernel program runs through BPF_PROG_TEST_RUN on frames built here, with the data-plane clock
set per packet (globals.clock_ns), so both pipelines see the same times.  Needs root and the
object `make` builds; skipped with the reason otherwise.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import select
import socket
import struct
import subprocess
import threading

import numpy as np
import pytest

from cell.dataplane.pipeline import ControlConstants, Pipeline
from cell.dataplane.tables import TP, Tables, TPBatch
from cell.robot import datagram, udp

xdp = pytest.importorskip("cell.dataplane.xdp.program")

if os.geteuid() != 0:
    pytest.skip("the bpf syscall needs root (CAP_BPF)", allow_module_level=True)
if not xdp.OBJECT.exists():
    pytest.skip(f"{xdp.OBJECT.name} not built (make bpf needs clang)", allow_module_level=True)

from cell.dataplane.xdp.backend import XdpPipeline, XdpTables  # noqa: E402

PORT = 50000
SRC = ("10.0.0.1", 40000)


def frame(recs: np.ndarray, src: tuple[str, int] = SRC, port: int = PORT) -> bytes:
    payload = recs.tobytes()
    eth = b"\x02\x00\x00\x00\x00\x02" + b"\x02\x00\x00\x00\x00\x01" + b"\x08\x00"
    ip = struct.pack(
        "!BBHHHBBH4s4s",
        0x45,
        0,
        20 + 8 + len(payload),
        0,
        0,
        64,
        17,
        0,
        socket.inet_aton(src[0]),
        socket.inet_aton("10.0.0.2"),
    )
    return eth + ip + struct.pack("!HHHH", src[1], port, 8 + len(payload), 0) + payload


HEADERS = 14 + 20 + 8


class Pair:
    """A numpy pipeline and the XDP program, given the same control-plane calls."""

    def __init__(self, constants: ControlConstants, capacity: int = 512) -> None:
        self.program = xdp.XdpProgram(capacity, constants.n_bits, len(constants.c1))
        self.program.globals["listen_port"] = socket.htons(PORT)
        self.xt = XdpTables(self.program)
        self.xp = XdpPipeline(self.xt, constants)
        self.nt = Tables(capacity, 1024, 12)
        self.np = Pipeline(self.nt, constants)

    def both(self, fn: str, *args: object, **kwargs: object) -> None:
        for obj in (self.nt, self.xt) if hasattr(self.nt, fn) else (self.np, self.xp):
            getattr(obj, fn)(*args, **kwargs)

    def close(self) -> None:
        self.program.close()

    def packet(self, recs: np.ndarray, now: int) -> tuple[np.ndarray, np.ndarray]:
        """The commands each pipeline makes of these records at `now`."""
        ours = recs.copy()
        self.np.process(ours, now, arrival=np.full(recs.size, now, np.int64))
        self.program.globals["clock_ns"] = now
        verdict, out = self.program.run(frame(recs))
        assert verdict == xdp.XDP_TX
        return ours, datagram.view(bytearray(out[HEADERS:]))

    def registers(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        n = self.nt.entities
        names = ("tp", "next_time", "stalled", "stall_ns", "dropped_ns", "dropped_why")
        out = {k: (getattr(self.nt, f"reg_{k}")[:n], getattr(self.xt, f"reg_{k}")[:n]) for k in names}
        for k in ("status_pos", "status_vel", "status_ns", "status_seq"):
            out[k] = (getattr(self.nt, k), getattr(self.xt, k))
        return out


def random_constants(rng: np.random.Generator) -> ControlConstants:
    return ControlConstants(
        tuple(rng.uniform(0.2, 1.5, 6).round(3)),
        tuple(rng.uniform(0.5, 40, 6).round(3)),
        int(rng.integers(4, 11)),
        tuple(rng.uniform(0.3, 4, 6).round(3)),
    )


def load_random_trajectories(pair: Pair, rng: np.random.Generator, t0: int) -> None:
    """Robots 1-6 alone, 7+8 merged; chains of TPs (a loop, a hold, a missing link), switches."""
    for r in range(1, 7):
        pair.both("add_robot", r)
    for t in (pair.nt, pair.xt):
        t.merge([7, 8])
    for r in range(1, 9):  # stale after 3 periods' jump, quiet after 40 ms
        pair.np.stale_periods[r] = pair.xp.stale_periods[r] = 3
        pair.np.quiet_ns[r] = pair.xp.quiet_ns[r] = 40_000_000
    for robot, joints in ((1, 6), (2, 6), (3, 6), (4, 6), (5, 6), (6, 6), (7, 12)):
        n = int(rng.integers(3, 20))
        ends = rng.choice(["loop", "hold", "missing"])
        tps = []
        for i in range(n):
            nxt = i + 1
            if i == n - 1:
                nxt = {"loop": 0, "hold": i, "missing": 999}[ends]
            tps.append(
                TP(
                    robot,
                    i,
                    nxt,
                    float(rng.choice([0.0005, 0.001, 0.002, 0.004, 0.008])),
                    rng.normal(0, 2, joints).tolist(),
                    rng.normal(0, 1.5, joints).tolist(),
                )
            )
        switches = [(robot, int(rng.integers(0, n)), int(rng.integers(0, n)))] if rng.random() < 0.5 else []
        start = t0 + int(rng.integers(0, 3e6))
        pair.both("update", insert=tps, switches=switches, registers=[(robot, 0, start)])


def statuses(rng: np.random.Generator, robot: int, joints: list[int], seq: int) -> np.ndarray:
    recs = datagram.empty(len(joints))
    recs["robot_id"], recs["joint_id"], recs["kind"], recs["seq"] = robot, joints, 0, seq
    scale = rng.choice([1e-3, 1.0, 1e3, 1e9])  # small, usual, large, clamped by INPUT_LIMIT
    recs["velocity"] = np.clip(rng.normal(0, 1, len(joints)) * scale * datagram.SCALE, -9e18, 9e18)
    recs["position"] = np.clip(rng.normal(0, 2, len(joints)) * scale * datagram.SCALE, -9e18, 9e18)
    return recs


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_random_tables_and_statuses_give_bit_identical_commands_and_registers(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pair = Pair(random_constants(rng))
    try:
        t = 1_000_000_000
        load_random_trajectories(pair, rng, t)
        seqs = dict.fromkeys(range(1, 12), 1)
        stepped = limited = 0
        for k in range(3000):
            gaps = [50_000, 300_000, 1_000_000, 2_000_000, 60_000_000]  # 60 ms: past the quiet bound
            t += int(rng.choice(gaps, p=[0.3, 0.3, 0.3, 0.09, 0.01]))
            robot = int(rng.choice([1, 2, 3, 4, 5, 6, 7, 8, 11]))  # 11: not configured (held at 0)
            seqs[robot] += 1 if rng.random() > 0.02 else int(rng.integers(2, 50))  # some watchdog jumps
            size = int(rng.choice([1, 2, 6, 6]))
            joints = sorted(rng.choice(6, size, replace=False).tolist())
            recs = statuses(rng, robot, joints, seqs[robot])
            if rng.random() < 0.1:  # a GSO batch mixing two robots
                other = int(rng.choice([1, 7, 8]))
                seqs[other] += 1
                more = statuses(rng, other, [0, 1, 2], seqs[other])  # (concatenate would make them native)
                recs = datagram.view(bytearray(recs.tobytes() + more.tobytes()))
            if k % 500 == 250:
                pair.both("stop", [3, 7, 8])
            if k % 500 == 400:
                pair.both("stop", [3, 7, 8], False)
            if k % 150 == 0:  # the controller sets the registers again (dropped trajectories restart)
                for r in (1, 2, 3, 4, 5, 6, 7):
                    tp = int(rng.integers(0, 3))
                    pair.both("update", registers=[(r, tp, t + int(rng.integers(0, 2e6)))])
            if k % 700 == 0:
                pair.both("set_stop_ramp", rng.uniform(1, 20, 6).tolist(), 0.008)
            ours, theirs = pair.packet(recs, t)
            assert theirs.tobytes() == ours.tobytes(), f"packet {k}: {ours} != {theirs}"
            if k % 100 == 0:
                for name, (a, b) in pair.registers().items():
                    assert np.array_equal(a, b), f"{name} differs after packet {k}"
        kernel = pair.program.counters()
        c = pair.np.counters
        names = ("packets", "holds", "steps", "resubmits", "stalls", "limited", "stop_commands", "dropped")
        for name in names:
            assert kernel[name] == getattr(c, name), name
        stepped, limited = c.steps, c.limited
        # the stream exercised what it is meant to: steps, resubmissions, limits, stalls, drops, stops
        assert stepped > 100 and c.resubmits > 0 and limited > 0 and c.stalls > 0
        assert c.dropped > 0 and c.stop_commands > 0 and c.holds > 0
    finally:
        pair.close()


def test_a_real_time_control_plane_holds_the_gate_at_a_priority_ceiling() -> None:
    """While the gate is closed the packet path waits on its holder: the holder (a SCHED_FIFO
    thread, as the dataplane process runs) is raised above anything else on its core, and gets its
    own priority back when it opens; statuses meanwhile are answered without the tables."""
    rng = np.random.default_rng(4)
    pair = Pair(random_constants(rng))
    seen: dict[str, object] = {}

    def control_plane() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
            pair.program.close_gate()
            seen["inside"] = os.sched_getparam(0).sched_priority
            verdict, _ = pair.program.run(frame(statuses(rng, 1, [0, 1], 2)))
            seen["verdict"] = verdict
            pair.program.open_gate()
            seen["after"] = os.sched_getparam(0).sched_priority
        except BaseException as exc:
            seen["error"] = exc

    try:
        load_random_trajectories(pair, rng, 1_000_000_000)
        gates, held = pair.program.gates, pair.program.counters()["held"]
        thread = threading.Thread(target=control_plane)
        thread.start()
        thread.join(10)
        assert "error" not in seen, seen.get("error")
        assert seen["inside"] == os.sched_get_priority_max(os.SCHED_FIFO) - 1
        assert seen["after"] == 10
        assert seen["verdict"] == xdp.XDP_TX
        assert pair.program.counters()["held"] == held + 2  # both records answered at the gate
        assert pair.program.gates == gates + 1
    finally:
        pair.close()


# --- the service: the program attached in a switch namespace, robots on the host's end ----------


def _recv(sock: socket.socket, timeout: float = 2.0) -> np.ndarray:
    """The next burst of commands (GRO may join several)."""
    ready, _, _ = select.select([sock], [], [], timeout)
    assert ready, "no answer"
    got = udp.recv_batch(sock)
    assert got is not None
    return datagram.view(bytearray(got[0]))


def test_the_service_answers_from_the_kernel_and_its_control_plane_writes_the_maps() -> None:
    from dataclasses import asdict

    from cell.config import XdpConfig, load_config
    from cell.dataplane.plane import XdpDataPlane
    from cell.dataplane.wire import encode_tps
    from cell.dataplane.xdp.switch import switch_namespace
    from cell.v1 import dataplane_pb2

    tag = f"cxt{os.getpid()}"[:12]
    net = XdpConfig(netns=tag, veth=tag, host_addr="10.197.0.1", switch_addr="10.197.0.2", prefix=24, cpu=-1)
    robots = [{"id": 1, "name": "x1", "skill_port": 23001}]
    dp = {"listen": f"10.197.0.2:{PORT}", "backend": "xdp", "xdp": asdict(net)}
    cfg = load_config(overrides={"robots": robots, "dataplane": dp})
    with switch_namespace(net):
        plane = XdpDataPlane(cfg)
        robot = udp.open_socket(net.host_addr)
        spoofer = udp.open_socket(net.host_addr)
        try:
            dst = (net.switch_addr, PORT)
            recs = datagram.empty(6)
            datagram.pack(recs, 1, np.arange(6), 0, 1, 0.2, 0.5)
            robot.sendto(recs.tobytes(), dst)
            held = _recv(robot)
            assert held.size == 6 and (held["kind"] == 1).all() and (held["velocity"] == 0).all()
            # a trajectory, loaded over the control plane's API: the kernel follows it at once
            req = dataplane_pb2.TableUpdate()
            encode_tps(TPBatch.of([TP(1, 7, 7, 1.0, [0.6] * 6, [0.0] * 6)]), req.insert)
            req.registers.add(robot_id=1, tp_id=7, next_time_ns=2**62)
            reply = asyncio.run(plane.update(req))
            assert reply.inserted == 1 and reply.loaded == 1
            assert 0 <= reply.apply_us < 50_000  # the gate was closed for the flip, briefly
            datagram.pack(recs, 1, np.arange(6), 0, 2, 0.2, 0.5)
            robot.sendto(recs.tobytes(), dst)
            moving = _recv(robot)
            # the same record through the numpy pipeline gives the same command, bit for bit
            ref_tables = Tables(64, 1024, 12)
            ref = Pipeline(ref_tables, plane.pipeline.constants)
            ref_tables.add_robot(1)
            ref_tables.update(insert=[TP(1, 7, 7, 1.0, [0.6] * 6, [0.0] * 6)], registers=[(1, 7, 2**62)])
            expect = recs.copy()
            ref.process(expect, 1)
            assert np.array_equal(moving["velocity"], expect["velocity"]) and (moving["velocity"] > 0).all()
            # bad input: counted and dropped, never answered; another sender for robot 1 is refused
            robot.sendto(b"\x00" * 23, dst)
            spoofer.sendto(recs[:1].tobytes(), dst)
            # a Responsive Link stop: the first stop commands leave from user space at once
            assert plane.stop_robots([1]) == 6
            stop = _recv(robot)
            assert (stop["kind"] == 1).all() and (np.abs(stop["velocity"]) < np.abs(moving["velocity"])).all()
            robot.sendto(recs.tobytes(), dst)  # and the kernel answers the next status from the StopRamp
            ramp = _recv(robot)
            assert np.array_equal(ramp["velocity"], stop["velocity"])
            c = plane.counters()
            assert c["rejected.length"] == 1 and c["rejected.spoofed"] == 1
            assert c["holds"] == 12 and c["stop_commands"] == 6 and c["dropped"] == 1  # (held, then stopped)
            assert c["commands_out"] == 24 and c["xdp.gates"] >= 2
            state = plane.state()
            assert state.robots[0].dropped_why == "stop" and state.robots[0].tp_id == -1
        finally:
            robot.close()
            spoofer.close()
            plane.close()
    names = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert tag not in names


async def test_a_detached_program_is_answered_for_from_user_space_and_attached_again() -> None:
    """Someone detaches the program (`ip link set dev ... xdpgeneric off`): the statuses then reach the
    control plane's socket.  It answers them through the program itself, at once, and attaches it
    again; a program put in its place is reported, not fought."""
    from dataclasses import asdict

    from cell.config import XdpConfig, load_config
    from cell.dataplane.plane import XdpDataPlane
    from cell.dataplane.xdp.switch import in_namespace, switch_namespace

    tag = f"cxd{os.getpid()}"[:12]
    net = XdpConfig(netns=tag, veth=tag, host_addr="10.198.0.1", switch_addr="10.198.0.2", prefix=24, cpu=-1)
    dp = {"listen": f"10.198.0.2:{PORT}", "backend": "xdp", "xdp": asdict(net)}
    cfg = load_config(overrides={"robots": [{"id": 1, "name": "x1", "skill_port": 23001}], "dataplane": dp})

    def xdp_on_port() -> str:
        out = subprocess.run(
            ["ip", "-n", tag, "-d", "link", "show", f"{tag}1"], capture_output=True, text=True
        )
        return out.stdout

    with switch_namespace(net):
        plane = XdpDataPlane(cfg)
        robot = udp.open_socket(net.host_addr)
        watcher = asyncio.create_task(plane.run())
        loop = asyncio.get_running_loop()
        try:
            recs = datagram.empty(6)
            dst = (net.switch_addr, PORT)

            async def exchange(seq: int) -> np.ndarray:
                datagram.pack(recs, 1, np.arange(6), 0, seq, 0.2, 0.5)
                robot.sendto(recs.tobytes(), dst)
                return await loop.run_in_executor(None, _recv, robot)

            first = await exchange(1)
            assert (first["kind"] == 1).all() and plane.counters()["xdp.answered_in_user_space"] == 0
            detach = ["ip", "-n", tag, "link", "set", "dev", f"{tag}1", "xdpgeneric", "off"]
            subprocess.run(detach, check=True)
            assert "xdpgeneric" not in xdp_on_port()
            robot.sendto(b"\x00" * 23, dst)  # junk, passed up too: dropped by the program, counted
            second = await exchange(2)  # answered all the same: from user space, by the program
            assert plane.counters()["rejected.length"] == 1
            assert second.size == 6 and (second["kind"] == 1).all() and (second["seq"] == 2).all()
            async with asyncio.timeout(5):  # (the attach runs in the namespace's thread meanwhile)
                while plane.counters()["xdp.reattached"] < 1:
                    await asyncio.sleep(0.01)
            assert plane.counters()["xdp.answered_in_user_space"] == 1
            assert f"id {plane.watch.prog_id}" in xdp_on_port()  # back on the port
            third = await exchange(3)  # and the kernel answers again, nothing passed up
            assert (third["seq"] == 3).all() and plane.counters()["xdp.answered_in_user_space"] == 1
            # a status that waited at the socket while the program, attached again, answered newer
            # ones: dropped, not run through it (it would read as a jump: a robot that lived without us)
            watcher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await watcher
            subprocess.run(detach, check=True)
            for seq in (2, 4):
                datagram.pack(recs, 1, np.arange(6), 0, seq, 0.2, 0.5)
                robot.sendto(recs.tobytes(), dst)
            await loop.run_in_executor(None, select.select, [plane.sock], [], [], 1.0)
            while plane._answer_passed():  # (until both have been read)
                pass
            fourth = await loop.run_in_executor(None, _recv, robot)
            assert (fourth["seq"] == 4).all() and plane.counters()["xdp.stale_passed"] == 1
            plane._check_attached()
            assert plane.counters()["xdp.reattached"] == 2
            # another program in its place (the bare reflector): reported, left alone
            other = xdp.XdpProgram(1, 2, 1)
            try:
                other_id = in_namespace(
                    tag, lambda: other.attach(socket.if_nametoindex(f"{tag}1"), reflect=True)
                )
                plane._check_attached()
                assert plane.watch.replaced_by == other_id and plane.counters()["xdp.replaced"] == 1
                assert f"id {other_id}" in xdp_on_port()
            finally:
                other.ifindex = None  # (the plane's close below detaches whatever is attached)
                other.close()
        finally:
            watcher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await watcher
            robot.close()
            plane.close()


def test_the_background_sweep_times_both_programs_beside_ordinary_traffic_and_cleans_up() -> None:
    """Sec. 7.1 on XDP, one point: the generator offers what was asked through the switch's program,
    probes come back through both the velocity-control pipeline and plain forwarding, and the switch's
    namespace and the generator are gone afterwards."""
    from cell.bench import background_xdp as bx
    from cell.dataplane.xdp.switch import missing

    if why := missing():
        pytest.skip(why)
    s = bx.sweep(seconds=0.5, frames=(64,), rates=(40,), rounds=1, log=lambda _line: None)
    (p,) = s.points
    assert p.frame == 64 and 0.8 * 40 <= p.offered_kpps <= 1.2 * 40
    assert p.offered_mbps == pytest.approx(p.offered_kpps * 1e3 * 64 * 8 / 1e6, rel=1e-6)
    assert 0 < p.forward_p50_us <= p.forward_p99_us and 0 < p.control_p50_us <= p.control_p99_us
    assert p.control_on_time >= 0.99
    assert s.figures()["apart_us_64"] == pytest.approx(p.control_p50_us - p.forward_p50_us)
    left = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert "cbb" not in left
