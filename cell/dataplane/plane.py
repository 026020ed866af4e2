"""The data plane's packet path: the Pipeline between UDP sockets (numpy) or the XDP program,
its control plane's handlers (update, merge, state, load_constants) and its Responsive Link node.

Status datagrams arrive on UDP [dataplane] listen; each wake-up takes every
datagram waiting (up to `batch`, with UDP GRO), runs them through the
pipelines in one numpy pass and answers each with a command to its sender
(UDP GSO).  The controller only changes tables, through the handlers here
(served on the bus by services/dataplane.py).

Stops and resumes come on the data plane's own Responsive Link node (its
event socket, read ahead of any status batch), never over the bus: a stop
sets the robots' REG_stop, clears their registers and sends each of them a
first stop command at once, from its last status; until a resume the
controller's register updates for them are refused (`stopped`).

One module, over 600 lines, on purpose: it is the switch, the P4 program's control flow and its
control plane around the tables and pipelines (cell.dataplane.tables, .pipeline), whichever backend
carries the packets; split, each half would need the other's state.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from cell import meter, models, sched
from cell.bus import FaultCode, RpcFault
from cell.config import CellConfig, parse_host_port
from cell.dataplane.egress import ROBOT, EgressPort
from cell.dataplane.forward import Forwarder
from cell.dataplane.ownership import Ownership
from cell.dataplane.pipeline import (
    DROP_QUIET,
    DROP_STOP,
    DROP_UNDERRUN,
    DROP_WATCHDOG,
    QUIET_NS,
    ControlConstants,
    Pipeline,
)
from cell.dataplane.tables import NO_ROW, Refused, Tables, TPBatch
from cell.dataplane.wire import decode_keys, decode_tps
from cell.dataplane.xdp.backend import XdpPipeline, XdpTables
from cell.dataplane.xdp.libbpf import BpfError
from cell.dataplane.xdp.program import XdpProgram
from cell.dataplane.xdp.switch import in_namespace, namespace_thread
from cell.rlink.leaf import LeafNode
from cell.rlink.station import Order
from cell.robot import datagram, udp
from cell.robot.datagram import SCALE, Kind
from cell.timer import realtime_offset
from cell.v1 import dataplane_pb2

log = logging.getLogger("cell.dataplane")

_STATUS = int(Kind.STATUS)
_DROP_WHY = {DROP_WATCHDOG: "watchdog", DROP_UNDERRUN: "underrun", DROP_STOP: "stop", DROP_QUIET: "quiet"}
SLICE = 1024  # records run through the pipeline between two looks at the event socket (a stop
# waits behind at most one slice: about 0.3 ms, against 0.6 ms for 2048, at ~8% more CPU per record)


def stop_decel(config: CellConfig) -> np.ndarray:
    """The StopRamp's braking per joint (rad/s^2): [rlink] stop_decel of the slowest deceleration any
    robot of the cell's models has at that joint (one ramp serves every robot, as one table)."""
    limits = [models.get(r.model).a_max for r in config.robots] or [models.get("ur5e").a_max]
    joints = max(len(a) for a in limits)
    slowest = [min(a[j] for a in limits if j < len(a)) for j in range(joints)]
    return np.array(slowest) * config.rlink.stop_decel


class DataPlane:
    """The packet path around a Pipeline: UDP in, commands out, everything counted."""

    def __init__(self, config: CellConfig) -> None:
        dp = config.dataplane
        constants = ControlConstants(tuple(dp.c1), tuple(dp.c2), dp.n_bits, tuple(dp.v_max))
        self.tables, self.pipeline, self.robot_joints = self._state(config, constants)
        self.merged: dict[int, list[int]] = {}  # entity -> its robots, for entities of several
        for r in config.robots:
            self.add_robot(r.id)
        window = min((1.0 / r.command_hz for r in config.robots), default=1 / 125)
        self.pipeline.set_stop_ramp(stop_decel(config), window)
        for r in config.robots:  # one window beyond the robot's watchdog: it has surely stopped
            self.pipeline.stale_periods[r.id] = (r.watchdog_windows + 1) * (r.status_hz // r.command_hz)
            self.pipeline.quiet_ns[r.id] = QUIET_NS
        self.boot_id = int.from_bytes(os.urandom(8), "little")  # tells a controller our tables are new
        self.ownership = Ownership()  # which controller has each robot (take-overs seen, not fought)
        self.poll: Callable[[], None] | None = None  # called between slices (the event socket)
        self.batch = dp.batch
        self.rejected = {"length": 0, "kind": 0, "joint": 0, "spoofed": 0}
        self.packets_in = self.commands_out = self.unsent = self.batches = 0
        self.batch_ns: list[int] = []
        self._update_lock = asyncio.Lock()
        self.egress: EgressPort | None = None
        self.forwarders: list[Forwarder] = []
        self._open(config)
        sched.settle_heap()  # what exists now lives as long as the service

    def _state(self, config: CellConfig, constants: ControlConstants) -> tuple[Tables, Pipeline, np.ndarray]:
        """The tables, the pipeline over them and each robot's joint count (0: not configured)."""
        dp = config.dataplane
        tables = Tables(dp.capacity, dp.max_entities, dp.max_joints)
        return tables, Pipeline(tables, constants), np.zeros(1 << 16, np.int64)

    def _open(self, config: CellConfig) -> None:
        """The packet path's sockets, egress port and forwarders."""
        dp = config.dataplane
        # each robot is pinned to the address its first status came from: another sender's statuses
        # for it are dropped (counted `spoofed`) until it has been quiet for QUIET_NS (a restart); a
        # mapped data plane's packet path pins them in its own maps (Pins reads them there)
        self.robot_addr: dict[int, tuple] | Pins = {}
        self.pin = np.full(1 << 16, -1, np.int32)  # robot -> its sender's number in _sender_ids
        self._sender_ids: dict[tuple, int] = {}
        self.sock = udp.open_socket(*parse_host_port(dp.listen), timestamps=True)
        self.sender = udp.Sender(self.sock, datagram.SIZE)
        eg = dp.egress
        # the port commands leave by, shared with forwarded traffic (Appendix C); None: no limit of ours
        if eg.rate_mbps > 0:
            self.egress = EgressPort(eg.rate_mbps * 1e6, int(eg.buffer_kb * 1024), eg.scheduling)
        try:
            self.forwarders += [Forwarder(rule) for rule in dp.forward]
        except BaseException:
            self.close()
            raise

    def add_robot(self, robot: int, joints: int = 6) -> None:
        self.tables.add_robot(robot, joints)
        self.robot_joints[robot] = joints

    def close(self) -> None:
        self.sock.close()
        for f in self.forwarders:
            f.close()

    def _emit(self, buf: memoryview, addr: tuple) -> None:
        """Commands to one robot: out at once, or into the egress port's robot queue."""
        if self.egress is None:
            self._wire(buf, datagram.SIZE, addr)
        else:
            n, now = len(buf) // datagram.SIZE, time.monotonic_ns()
            self.unsent += n - self.egress.enqueue(ROBOT, bytes(buf), datagram.SIZE, addr, self._wire, now)

    def _wire(self, buf: memoryview, _seg: int, addr: tuple) -> int:
        """Commands onto the wire (the egress port's way out for them, or at once without one)."""
        sent = self.sender.send(buf, addr)
        self.commands_out += sent
        self.unsent += len(buf) // datagram.SIZE - sent
        return sent

    # --- the packet path ---------------------------------------------------------------------

    def handle(self) -> int:
        """Answer every status datagram waiting (up to `batch`); return how many were answered."""
        chunks: list[bytes] = []
        counts: list[int] = []
        senders: list[tuple] = []
        stamps: list[int] = []  # each chunk's kernel receive time (CLOCK_REALTIME)
        total = 0
        size = datagram.SIZE
        while total < self.batch:
            got = udp.recv_batch(self.sock)
            if got is None:
                break
            good, bad = udp.whole_datagrams(got[0], got[1], size)
            self.rejected["length"] += bad
            if good:
                chunks.append(good)
                counts.append(len(good) // size)
                senders.append(got[2])
                stamps.append(got[3])
                total += len(good) // size
        if not chunks:
            return 0
        t0 = time.perf_counter_ns()
        now = time.monotonic_ns()
        # the packets' arrival on this clock; a chunk without a timestamp counts as arriving now
        rx = np.array(stamps, np.int64) - (time.time_ns() - now)
        rx[(rx > now) | (np.array(stamps) == 0)] = now
        # join bytes, then view: np.concatenate would turn the wire's big-endian fields native
        recs = datagram.view(bytearray(b"".join(chunks)))
        owner = np.repeat(np.arange(len(chunks)), counts)
        self.packets_in += recs.size
        bad_kind = recs["kind"] != _STATUS
        joints = self.robot_joints[recs["robot_id"]]
        bad_joint = ~bad_kind & (joints > 0) & (recs["joint_id"] >= joints)
        ok = ~(bad_kind | bad_joint)
        if not ok.all():
            self.rejected["kind"] += int(bad_kind.sum())
            self.rejected["joint"] += int(bad_joint.sum())
            recs, owner = recs[ok], owner[ok]
        arrival = rx[owner]
        sid = np.array([self._sender_ids.get(s, -2) for s in senders], np.int32)[owner]
        strange = self.pin[recs["robot_id"]] != sid
        if strange.any():
            spoofed = self._check_senders(recs["robot_id"], owner, strange, senders, now)
            if spoofed.any():
                self.rejected["spoofed"] += int(spoofed.sum())
                recs, owner, arrival = recs[~spoofed], owner[~spoofed], arrival[~spoofed]
        if recs.size <= SLICE or self.poll is None:
            self.pipeline.process(recs, now, arrival=arrival)
        else:
            for i in range(0, recs.size, SLICE):
                self.pipeline.process(recs[i : i + SLICE], now, stops=False, arrival=arrival[i : i + SLICE])
                self.poll()  # a stop comes in here, ahead of the rest of the batch
            if self.pipeline.stopping:
                self.pipeline.apply_stops(recs)  # once, over every slice: before the stop or after
        # answer each sender with its own records, in one sendto each
        answered = np.bincount(owner, minlength=len(chunks))
        raw = recs.view(np.uint8).data
        start = 0
        for k in np.flatnonzero(answered).tolist():
            n = int(answered[k])
            self._emit(raw[start * size : (start + n) * size], senders[k])
            start += n
        self.batches += 1
        self.batch_ns.append(time.perf_counter_ns() - t0)
        if len(self.batch_ns) > 8192:
            del self.batch_ns[:4096]
        return recs.size

    def _check_senders(
        self, robot: np.ndarray, owner: np.ndarray, strange: np.ndarray, senders: list[tuple], now: int
    ) -> np.ndarray:
        """Pin robots heard of first (or again after QUIET_NS of silence); mark the records of the rest."""
        bad: list[int] = []
        fresh: set[int] = set()  # pinned in this batch: a second sender for it is not a restart
        pairs = np.unique(np.stack([robot[strange], owner[strange]], axis=1), axis=0)
        for r, k in pairs.tolist():
            if self.robot_addr.get(r) == senders[k]:
                continue
            if self.pin[r] < 0 or (r not in fresh and now - int(self.tables.status_ns[r]) > QUIET_NS):
                self._pin(r, senders[k])
                fresh.add(r)
            else:
                bad.append(r << 20 | k)
        key = robot.astype(np.int64) << 20 | owner
        return np.isin(key, bad) if bad else np.zeros(robot.size, bool)

    def _pin(self, robot: int, addr: tuple) -> None:
        pinned = self.robot_addr
        assert isinstance(pinned, dict)  # (the packet path in Python pins them itself)
        pinned[robot] = addr
        if addr not in self._sender_ids:
            if len(self._sender_ids) > 2 * len(pinned) + 64:  # forget senders no robot uses
                used = set(pinned.values())
                self._sender_ids = {a: i for a, i in self._sender_ids.items() if a in used}
            self._sender_ids[addr] = max(self._sender_ids.values(), default=-1) + 1
        self.pin[robot] = self._sender_ids[addr]

    async def sweep(self, period: float = 0.05) -> None:
        """Drop the trajectories of robots gone quiet (Pipeline.sweep), every `period`, until cancelled
        (QUIET_NS is 500 ms: a sweep every 50 ms finds them within a tenth more, at a fifth of the
        event-loop time of one every 10 ms)."""
        robots = np.flatnonzero(self.pipeline.quiet_ns > 0)
        while True:
            await asyncio.sleep(period)
            self.pipeline.sweep(robots, time.monotonic_ns())

    async def run(self) -> None:
        """Handle datagrams as they come, until cancelled: this process's Python is the packet path
        here, at its group's real-time priority."""
        for problem in meter.real_time_loop(sched.LOOP_PRIORITY):
            log.warning("%s", problem)
        loop = asyncio.get_running_loop()
        ready = asyncio.Event()
        fd = self.sock.fileno()
        loop.add_reader(fd, ready.set)
        for f in self.forwarders:
            loop.add_reader(f.sock.fileno(), ready.set)
        try:
            while True:
                await ready.wait()
                ready.clear()
                while True:  # robot statuses first, then a budget of each forwarder's bursts
                    more = self.handle() >= self.batch
                    for f in self.forwarders:
                        more |= f.handle(self.egress) >= f.budget
                    if not more:
                        break
                    await asyncio.sleep(0)  # more may be waiting: after yielding to the rest of the service
        finally:
            loop.remove_reader(fd)
            for f in self.forwarders:
                loop.remove_reader(f.sock.fileno())

    async def pump(self) -> None:
        """Send what the egress port has queued as its wire frees up, until cancelled."""
        if self.egress is None:
            return
        while True:
            wait = self.egress.transmit(time.monotonic_ns())
            # nothing queued: look again soon (an enqueue sends at once whatever the wire allows)
            await asyncio.sleep(0.001 if wait is None else wait / 1e9)

    # --- stops (from the Responsive Link) -----------------------------------------------------

    def _entity_robots(self, robots: list[int]) -> list[int]:
        """The robots and every robot merged with one of them (an entity stops as one)."""
        ent = self.tables.robot_entity
        out = set(robots)
        for r in robots:
            out.update(self.merged.get(int(ent[r]), ()))
        return sorted(out)

    def stop_robots(self, robots: list[int]) -> int:
        """REG_stop on, registers cleared, and a first stop command to each robot now; how many sent."""
        robots = self._entity_robots(robots)
        t, sent = self.tables, 0
        self.pipeline.stop(robots)
        # registers cleared as a drop, noted: a controller that missed the link's news still learns of it
        ent = t.robot_entity[robots].astype(np.int64)
        self.pipeline.drop(ent[ent != NO_ROW], time.monotonic_ns(), DROP_STOP)
        for r in robots:
            addr, n = self.robot_addr.get(r), int(self.robot_joints[r])
            if addr is None or not t.status_ns[r] or n == 0:
                continue  # never heard of: its first status is answered with the ramp anyway
            recs = datagram.empty(n)
            recs["robot_id"], recs["joint_id"], recs["kind"] = r, np.arange(n), Kind.COMMAND
            recs["position"] = t.status_pos[r, :n]
            recs["velocity"] = self.pipeline.ramp(t.status_vel[r, :n].copy(), np.arange(n))
            before = self.commands_out
            self._emit(recs.view(np.uint8).data, addr)
            sent += self.commands_out - before
        return sent

    def resume_robots(self, robots: list[int]) -> None:
        """REG_stop off: the robots hold where they are (registers clear) until the controller loads."""
        self.pipeline.stop(self._entity_robots(robots), False)

    def stopped(self, robot: int) -> bool:
        return bool(self.pipeline.reg_stop[self._entity_robots([robot])].any())

    # --- the control plane -------------------------------------------------------------------

    async def update(self, req: dataplane_pb2.TableUpdate) -> dataplane_pb2.UpdateReply:
        """Apply one atomic batch in slices, letting the packet path run between them."""
        async with self._update_lock:  # one update at a time: the staged update relies on it
            started = slice_start = time.perf_counter_ns()
            longest = 0

            async def pause() -> None:
                """End a slice (the longest counts as the hold-up) and let the packet path run."""
                nonlocal longest, slice_start
                longest = max(longest, time.perf_counter_ns() - slice_start)
                await asyncio.sleep(0)
                slice_start = time.perf_counter_ns()

            try:
                insert, remove = decode_tps(req.insert), decode_keys(req.remove)
            except ValueError as exc:
                raise RpcFault(FaultCode.BAD_REQUEST, str(exc)) from None
            robots = _robots_of(req, insert, remove)
            if taken := self.ownership.refused(req.controller, robots):
                raise RpcFault(
                    FaultCode.TAKEN,
                    f"robot(s) {taken} taken over by another controller since this one loaded them (it "
                    "flushed their tables as it started): this one has lost them",
                )
            held = [r.robot_id for r in req.registers if not r.clear and self.stopped(r.robot_id)]
            try:
                flushed = [k for r in req.flush_robots for k in self.tables.keys_of(r)]
            except Refused as exc:
                raise RpcFault(exc.code, exc.reason) from None
            if flushed:
                remove = np.concatenate([remove, np.array(flushed, np.int64).reshape(-1, 2)])
            registers = [(r, None, 0) for r in req.flush_robots]
            if held:
                raise RpcFault(
                    FaultCode.STOPPED, f"robot(s) {held} stopped over the Responsive Link: resume first"
                )
            await pause()
            steps = self.tables.staged_update(
                insert=insert,
                remove=remove,
                switches=[(s.robot_id, s.tp_id, None if s.unset else s.next_id) for s in req.switches],
                registers=registers
                + [(r.robot_id, None if r.clear else r.tp_id, r.next_time_ns) for r in req.registers],
            )
            try:
                while True:
                    try:
                        next(steps)
                    except StopIteration as done:
                        removed = int(done.value)
                        break
                    except Refused as exc:
                        raise RpcFault(exc.code, exc.reason) from None
                    await pause()
            finally:
                steps.close()  # cancelled mid-way: the staged rows go back (GeneratorExit in the update)
            longest = max(longest, time.perf_counter_ns() - slice_start)  # the last slice
            self.ownership.applied(req.controller, robots, req.flush_robots)
            return dataplane_pb2.UpdateReply(
                inserted=len(insert),
                removed=removed,
                loaded=self.tables.loaded,
                capacity=self.tables.capacity,
                apply_us=longest / 1e3,
                total_ms=(time.perf_counter_ns() - started) / 1e6,
                now_ns=time.monotonic_ns(),
                boot_id=self.boot_id,
            )

    async def load_constants(self, req: dataplane_pb2.Constants) -> dataplane_pb2.ConstantsReply:
        """New controller constants: tables built in a worker thread, then swapped in at once."""
        constants = ControlConstants(tuple(req.c1), tuple(req.c2), req.n_bits, tuple(req.v_max))
        if len(constants.c1) != self.pipeline.joints:
            raise RpcFault(FaultCode.BAD_REQUEST, f"{self.pipeline.joints} values per list expected")
        t0 = time.perf_counter()
        try:
            built = await asyncio.to_thread(Pipeline.build, constants)
        except ValueError as exc:
            raise RpcFault(FaultCode.BAD_REQUEST, str(exc)) from None
        build_ms = (time.perf_counter() - t0) * 1e3
        self.pipeline.install(built)
        p = self.pipeline
        entries = p.transform_curr_velocity.entries + p.transform_trg_velocity.entries
        return dataplane_pb2.ConstantsReply(
            transform_entries=entries + p.transform_diff_position.entries,
            limit_entries=p.limit_velocity.entries,
            build_ms=build_ms,
        )

    def merge(self, req: dataplane_pb2.MergeRequest) -> dataplane_pb2.MergeReply:
        try:
            entity = self.tables.merge(list(req.robot_ids))
            self.merged[entity] = list(req.robot_ids)
            return dataplane_pb2.MergeReply(entity=entity)
        except Refused as exc:
            raise RpcFault(exc.code, exc.reason) from None

    def counters(self) -> dict[str, float]:
        c = self.pipeline.counters
        out: dict[str, float] = {
            "packets_in": self.packets_in,
            "commands_out": self.commands_out,
            "unsent": self.unsent,
            "send_errors": self.sender.errors,  # (of those unsent, the ones the network refused)
            "batches": self.batches,
            "holds": c.holds,
            "steps": c.steps,
            "resubmits": c.resubmits,
            "stalls": c.stalls,
            "limited": c.limited,
            "stop_commands": c.stop_commands,
            "dropped": c.dropped,
            "dropped.stop": c.dropped_stop,
            "tps_loaded": self.tables.loaded,
        }
        out.update({f"rejected.{k}": v for k, v in self.rejected.items()})
        if self.egress is not None:
            out.update({f"egress.{k}": v for k, v in self.egress.summary().items()})
        for f in self.forwarders:
            out.update({f"forward.{f.name}.{k}": getattr(f, k) for k in ("received", "sent", "dropped")})
        if self.batch_ns:
            ns = sorted(self.batch_ns)
            out["batch_p50_us"] = ns[len(ns) // 2] / 1e3
            out["batch_p99_us"] = ns[min(len(ns) - 1, int(len(ns) * 0.99))] / 1e3
        return out

    def state(
        self, req: dataplane_pb2.StateRequest | None = None, with_robots: bool = True
    ) -> dataplane_pb2.DataplaneState:
        """The tables' state (every robot's registers, or those `req` names) and the counters;
        with_robots=False: the counters alone (telemetry: a fleet's thousand robots cost a scan each time)."""
        t = self.tables
        brief = req is not None and req.robots_only
        mono = time.monotonic_ns()
        # (the process's one offset, the narrowest of many bracketed reads: a pair of reads here was
        # off by whatever ran between them, and the robots' process, above this one on its core,
        # can: that error went into the offset controllers place their starts on the tick grid by,
        # a start 0.2-0.9 of a period off the robots' grid in fresh-clone runs)
        st = dataplane_pb2.DataplaneState(
            now_ns=mono,
            loaded=t.loaded,
            capacity=t.capacity,
            boot_id=self.boot_id,
            realtime_offset_ns=realtime_offset(),
        )
        if not brief:
            st.counters.update(self.counters())
        if not with_robots:
            return st
        if req is not None and req.robot_ids:  # (the usual read: a few robots; no scan of all ids)
            known = len(t.robot_entity)
            robots = sorted({r for r in req.robot_ids if 0 <= r < known and t.robot_entity[r] != NO_ROW})
        else:
            robots = np.flatnonzero(t.robot_entity != NO_ROW).tolist()
        if not robots:
            return st
        # (the registers gathered for all the robots at once: a fleet's thousand robots, one at a time
        # through numpy scalars, took 23 ms a read)
        stop = self.pipeline.reg_stop
        rows = np.asarray(robots, np.int64)
        ents = t.robot_entity[rows].astype(np.int64)
        # (stopped()'s, for the merged entities read only: all of a fleet's hundred pairs looked at in
        # each of its thousand robots' reads were two thirds of the data plane's Python)
        merged = self.merged.keys() & set(ents.tolist())
        stopped_merged = {e for e in merged if stop[self.merged[e]].any()}
        columns = zip(
            robots,
            ents.tolist(),
            self.robot_joints[rows].tolist(),
            t.reg_next_time[ents].tolist(),
            (t.status_pos[rows] / SCALE).tolist(),
            (t.status_vel[rows] / SCALE).tolist(),
            t.status_ns[rows].tolist(),
            t.reg_dropped_ns[ents].tolist(),
            t.reg_stalled[ents].tolist(),
            t.reg_dropped_why[ents].tolist(),
            stop[rows].tolist(),
            strict=True,
        )
        for robot, e, n, next_ns, pos, vel, status_ns, dropped_ns, stalled, why, stopped in columns:
            tp = t.current_tp(robot)
            st.robots.add(
                robot_id=robot,
                entity=e,
                tp_id=-1 if tp is None else tp,
                next_time_ns=next_ns,
                position=pos[:n],
                velocity=vel[:n],
                status_ns=status_ns,
                dropped_ns=dropped_ns,
                stalled=bool(stalled),
                dropped_why=_DROP_WHY.get(why, ""),
                stopped=bool(stopped) or e in stopped_merged,
                controller=self.ownership.owner.get(robot, 0),
            )
        return st


def _robots_of(req: dataplane_pb2.TableUpdate, insert: TPBatch, remove: np.ndarray) -> set[int]:
    """The robots an update loads, removes, switches or sets registers of, those it flushes aside
    (a take-over: what it flushes becomes its own)."""
    robots = {*insert.robot.tolist(), *remove[:, 0].tolist()}
    robots |= {s.robot_id for s in req.switches} | {r.robot_id for r in req.registers}
    return robots - set(req.flush_robots)


# SCHED_FIFO of the data plane's control plane (its Python) where the packet path runs elsewhere (the
# native data plane's C thread, the kernel's XDP program): under the packet path, over every normal
# process.  Its table updates are time-bound (a fired motion's switch must be in the tables before
# the robots' next status): at nice -10 a loaded test run saw one arm of two leave a period late
# half the time, and the controller's reads go unanswered for 0.7 s
CONTROL_PRIORITY = 1


class MappedDataPlane(DataPlane):
    """A packet path in C over tables in mapped memory (the XDP program's maps, the native data
    plane's arrays): this process is the control plane around it, with the same bus API, Responsive
    Link stops, sweep and state as the numpy backend, writing the memory the packet path reads."""

    program: Any  # XdpProgram or NativeProgram: the maps as numpy arrays, the gate, the counters
    prefix = ""  # of its own counters ("xdp.", "native.")

    def _program(self, config: CellConfig) -> Any:
        raise NotImplementedError

    def _state(self, config: CellConfig, constants: ControlConstants) -> tuple[Tables, Pipeline, np.ndarray]:
        self.program = self._program(config)
        try:
            tables = XdpTables(self.program, config.dataplane.max_joints)
            return tables, XdpPipeline(tables, constants), self.program.robots["joints"]
        except BaseException:
            self.program.close()
            raise

    async def update(self, req: dataplane_pb2.TableUpdate) -> dataplane_pb2.UpdateReply:
        """As the numpy backend's; apply_us is how long the packet path was held (the gate closed for
        the flip), since the slices in between do not stop it."""
        since = self.program.gates
        reply = await super().update(req)
        held = self.program.closed_ns[-(self.program.gates - since) :] if self.program.gates > since else [0]
        reply.apply_us = max(held) / 1e3
        return reply

    async def load_constants(self, req: dataplane_pb2.Constants) -> dataplane_pb2.ConstantsReply:
        try:
            XdpPipeline.check_fits(self.program, ControlConstants(tuple(req.c1), (), req.n_bits, ()))
        except BpfError as exc:
            raise RpcFault(FaultCode.BAD_REQUEST, str(exc)) from None
        return await super().load_constants(req)

    def counters(self) -> dict[str, float]:
        out = super().counters()
        k, user = self.program.counters(), self.pipeline.counters
        for name in ("holds", "steps", "resubmits", "stalls", "limited"):
            out[name] = k[name]
        out["dropped"] = k["dropped"] + user.dropped  # (the control plane drops too: sweeps, stops)
        out["stop_commands"] = k["stop_commands"] + user.stop_commands
        refused = ("kind", "joint", "spoofed", "batch")
        # (every status that came in: stepped, answered at the gate, or refused; commands_out counts
        # the gate's answers too, and a test once saw 6 more commands out than statuses in)
        out["packets_in"] = k["packets"] + k["held"] + sum(k[f"rejected.{r}"] for r in refused)
        out["commands_out"] = k["commands_out"] + self.commands_out
        out.update({n: k[n] for n in k if n.startswith("rejected.")})
        p = self.prefix
        out[f"{p}gates"], out[f"{p}held"], out[f"{p}datagrams"] = (
            self.program.gates,
            k["held"],
            k["datagrams"],
        )
        out[f"{p}gate_us_max"] = max(self.program.closed_ns, default=0) / 1e3  # (the recent 4,096)
        return out


class XdpDataPlane(MappedDataPlane):
    """The packet path as an XDP program in the switch's network namespace (cell/dataplane/xdp):
    the kernel answers every status."""

    prefix = "xdp."

    def _program(self, config: CellConfig) -> Any:
        dp = config.dataplane
        return XdpProgram(dp.capacity, dp.n_bits, len(dp.c1))

    def _open(self, config: CellConfig) -> None:
        dp, x = config.dataplane, config.dataplane.switch
        host, port = parse_host_port(dp.address)
        g = self.program.globals
        g["listen_addr"] = int.from_bytes(socket.inet_aton(host), "little")  # (network order in memory)
        g["listen_port"] = socket.htons(port)
        self.robot_addr = Pins(self.program.robots)
        self.netns, self.port = x.netns, f"{x.veth}1"
        self.watch = XdpWatch()

        def attach() -> socket.socket:
            self.watch.prog_id = self.program.attach(socket.if_nametoindex(self.port))
            # the user-space end: the first stop commands the Responsive Link asks for at once, and
            # the statuses that reach it when the program is not attached
            return udp.open_socket(host, port)

        try:
            self.sock = in_namespace(x.netns, attach)
        except BaseException:
            self.program.close()
            raise
        self.sender = udp.Sender(self.sock, datagram.SIZE)

    def close(self) -> None:
        self.sock.close()
        with contextlib.suppress(OSError, RuntimeError):  # (the namespace may be gone already)
            in_namespace(self.netns, self.program.detach)
        self.program.close()

    async def run(self) -> None:
        """The kernel answers every status; this watches that the program stays attached.  A status
        that reaches this process's socket is one the program did not see (someone detached it:
        `ip link set dev <veth>1 xdpgeneric off`, a tool that cleans up XDP programs): it is answered
        at once through the very program (BPF_PROG_TEST_RUN on its maps), and the program is
        attached again meanwhile (in a thread inside the namespace: an attach takes ~15 ms of
        statuses).  Another program attached in its place is reported, not fought."""
        # (the kernel answers the statuses: the control plane is this process's real-time thread, its
        # holds counted as a packet path's are)
        for problem in meter.real_time_loop(CONTROL_PRIORITY):
            log.warning("%s", problem)
        loop = asyncio.get_running_loop()
        passed, look = asyncio.Event(), asyncio.Event()
        # (its attaches off this process's CPUs: the packet path's core, which it shares with the robots)
        pinned = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else set()
        netns = namespace_thread(self.netns, frozenset(pinned))
        loop.add_reader(self.sock.fileno(), passed.set)

        async def answer() -> None:
            while True:
                await passed.wait()
                passed.clear()
                if self._answer_passed():
                    look.set()

        async def watch() -> None:
            while True:
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(XdpWatch.PERIOD_S):
                        await look.wait()
                look.clear()
                t0 = time.monotonic_ns()
                try:
                    found, now = await loop.run_in_executor(netns, self._attached_or_attach)
                except (OSError, RuntimeError) as exc:
                    log.warning("cannot check the XDP program on %s: %s", self.port, exc)
                    continue
                self.watch.checked(found, now, self.port, (time.monotonic_ns() - t0) / 1e6)

        try:
            async with asyncio.TaskGroup() as tg:
                tg.create_task(answer(), name="xdp-passed")
                tg.create_task(watch(), name="xdp-watch")
        finally:
            with contextlib.suppress(ValueError, OSError):  # (the socket may be closed already)
                loop.remove_reader(self.sock.fileno())
            netns.shutdown(wait=False)

    def _answer_passed(self) -> int:
        """Answer, through the program, the statuses waiting at the socket; how many there were.  A
        status older than what the program last saw of its robot is dropped unanswered (counted): it
        waited here while the program, attached again, answered newer ones, and run through it now
        it would read as a jump in status numbers (a robot that lived without us)."""
        seen = 0
        seqs, heard = self.program.robots["status_seq"], self.program.robots["status_ns"]
        for _ in range(XdpWatch.BURSTS):
            got = udp.recv_batch(self.sock)
            if got is None:
                break
            data, seg, src, _ = got
            for off in range(0, len(data), max(seg, 1)):
                seen += 1
                one = data[off : off + seg]
                if len(one) % datagram.SIZE == 0 and one:
                    recs = np.frombuffer(one, datagram.DTYPE)
                    robot = recs["robot_id"].astype(np.int64)
                    known = robot < len(seqs)
                    known[known] &= heard[robot[known]] > 0  # (a robot never heard has no last)
                    ahead = (recs["seq"][known].astype(np.int64) - seqs[robot[known]]) & 0xFFFFFFFF
                    if known.all() and ((ahead == 0) | (ahead >= 1 << 31)).all():
                        self.watch.stale += 1
                        continue
                out = self.program.answer(one, src[:2])
                if out is not None:
                    self.sock.sendto(out, src[:2])
                    self.watch.answered += 1
        return seen

    def _attached_or_attach(self) -> tuple[int, int]:
        """(In the namespace.)  The id of the program found on the port, and of the one there now:
        ours attached again if none was."""
        found = self.program.attached()
        if found == 0:
            return found, self.program.attach(socket.if_nametoindex(self.port))
        return found, found

    def _check_attached(self) -> None:
        """As the watch does, from any thread (tests)."""
        t0 = time.monotonic_ns()
        found, now = in_namespace(self.netns, self._attached_or_attach)
        self.watch.checked(found, now, self.port, (time.monotonic_ns() - t0) / 1e6)

    def counters(self) -> dict[str, float]:
        out = super().counters()
        out.update(self.watch.counters())
        return out


class XdpWatch:
    """What the control plane saw of its program's attachment (XdpDataPlane.run)."""

    PERIOD_S = 1.0  # a check this often with no status passed up (a program put in ours' place)
    BURSTS = 256  # socket reads per wake: a flood of passed-up datagrams cannot hold the loop

    def __init__(self) -> None:
        self.prog_id = 0  # ours, as attached
        self.reattached = 0
        self.answered = 0  # statuses answered from user space, through the program
        self.stale = 0  # of those passed up, older than the program's last of their robot: dropped
        self.replaced_by = 0  # another program's id, while one holds our port

    def checked(self, found: int, now: int, port: str, took_ms: float) -> None:
        if found == 0:
            self.reattached += 1
            self.prog_id, self.replaced_by = now, 0
            log.warning(
                "the XDP program was detached from %s: attached again in %.1f ms (%d statuses answered "
                "from user space so far)", port, took_ms, self.answered,
            )  # fmt: skip
        elif found != self.prog_id and found != self.replaced_by:
            self.replaced_by = found
            log.error(
                "another XDP program (id %d) is attached to %s in place of the cell's (id %d): the robots "
                "are not ours to command until it is removed (`ip link set dev %s xdpgeneric off`)",
                found, port, self.prog_id, port,
            )  # fmt: skip
        elif found == self.prog_id:
            self.replaced_by = 0

    def counters(self) -> dict[str, float]:
        return {
            "xdp.reattached": self.reattached,
            "xdp.answered_in_user_space": self.answered,
            "xdp.stale_passed": self.stale,
            "xdp.replaced": float(self.replaced_by != 0),
        }


class Pins:
    """The robots' pinned senders as the XDP program keeps them (robot -> (host, port))."""

    def __init__(self, robots: np.ndarray) -> None:
        self.robots = robots

    def get(self, robot: int) -> tuple[str, int] | None:
        r = self.robots[robot]
        if not r["pinned"]:
            return None
        return socket.inet_ntoa(int(r["pin_addr"]).to_bytes(4, "little")), socket.ntohs(int(r["pin_port"]))


class PlaneNode(LeafNode):
    """The data plane's Responsive Link node: its orders act on the tables at once, between batches."""

    role = "dataplane"

    def __init__(self, plane: DataPlane, config: CellConfig) -> None:
        super().__init__(config, {r.id for r in config.robots})
        self.plane = plane
        plane.poll = self.link.poll_events
        self.stop_us: list[float] = []  # event read -> first stop commands sent, recent

    def apply(self, order: Order) -> None:
        if order.stop:
            self.plane.stop_robots(order.robots)
            self.stop_us.append((time.perf_counter_ns() - self.link.arrived_ns) / 1e3)
            del self.stop_us[:-1024]
        else:
            self.plane.resume_robots(order.robots)

    def add_robot(self, robot: int) -> None:
        self.station.robots.add(robot)

    def counters(self) -> dict[str, float]:
        out = super().counters()
        if self.stop_us:
            out["rlink.stop_us_max"] = max(self.stop_us)
        return out
