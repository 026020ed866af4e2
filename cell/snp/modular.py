"""The SpW-SnP-MR modular robot, sans IO: a master node and its joint modules.

Both ends are state machines fed datagrams and times, returning datagrams to send
(`cell/snp/runner.py` puts them on UDP sockets).

The master
- explores its ports (SpaceWire router ports; here UDP addresses) with NODE_INFO_QUERY,
  learns each module's id, what it is plugged to and the items it offers, works out the
  chain from the base plate (a module's joint index is its depth), and configures it
  (CONFIGURE: its joint, the cycle period and phase, the query budget, its control
  parameters); a module that answers while the cycle runs is included without a restart
  (plug and operate);
- sends each subscriber SnP-TSP beacons at the period it asked for;
- answers the modules' time-bounded queries (SnP-MrT, through `Handler`: earliest deadline
  first, denied when the deadline cannot be met), or, in the baseline, takes their RMAP
  writes and writes the answers back;
- watches every included module (FDIR by data obsolescence): a module whose A did not come in
  a cycle is guessed (its last state, extrapolated), one silent for `suspect_cycles` is
  reported, one silent for `lost_ns` is excluded and its port explored again.

A joint module waits to be configured, subscribes to beacons and servos its clock, then
runs its cycle on the master's time grid: [A, B] (its state at T1; the desired velocity at
T3) and [C, D] (its desired force; the torque), each answered before its deadline or
replaced by a guess (no retry).  With transport "rmap" it writes A and C to the master's
memory as acknowledged RMAP writes (fixed timeout, one retry) and is written B and D.
"""

from __future__ import annotations

import math
import struct
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from cell.counters import Counters
from cell.snp import rmap
from cell.snp.handler import Handler
from cell.snp.packet import (
    Configure,
    Configured,
    Denied,
    Header,
    Item,
    ModuleKind,
    NodeInfo,
    NodeInfoQuery,
    PacketError,
    PacketType,
    Pid,
    Quantity,
    Query,
    QueryShape,
    Reply,
    TimeBeacon,
    TimeFollowUp,
    TimeRequest,
    TimeResponse,
    TimeSubscribe,
    TimeSubscribed,
    decode,
    encode,
    follow_up,
    query_shape,
    reply_shape,
    split_item_id,
)
from cell.snp.tsp import BeaconSchedule, ClockServo, on_grid

ROBOT = 0  # item ids of the modular robot: robot 0
TORQUE, FORCE = 5, 6  # quantities it adds to the cell's
MASTER_LA = 0xFE  # logical addresses (RMAP)
MODULE_LA0 = 0x20
A_BASE, C_BASE = 0x1000, 0x2000  # master memory: A and C of joint j at BASE + 16 j
B_ADDR, D_ADDR = 0x0000, 0x0010  # module memory
_MSG = struct.Struct("!ffQ")  # value, value, timestamp
_BEACON_FOLLOW_UPS_MISSED = 3  # beacons in a row without their follow-up: the master stopped them
_EXCHANGES = 8  # two-way exchanges a module makes for the path delay (the least queued is kept)


def item(quantity: int, joint: int) -> int:
    return (ROBOT << 16) | (quantity << 8) | joint


# The cycle's packets, each one shape (cell.snp.packet.QueryShape): A (position and velocity in,
# the desired velocity wanted), C (the desired force in, the torque wanted), and their answers.
_A, _C, _ANSWER = query_shape(2, 1), query_shape(1, 1), reply_shape(1)
# per joint: its position, velocity, desired velocity, force and torque item ids
_CYCLE_QUANTITIES = (Quantity.POSITION, Quantity.VELOCITY, Quantity.COMMANDED_VELOCITY, FORCE, TORQUE)
_IDS = [tuple(item(q, j) for q in _CYCLE_QUANTITIES) for j in range(256)]


class NodeState(StrEnum):
    """A module as the master's FDIR sees it."""

    FOUND = "found"  # explored, not configured yet
    CONFIGURING = "configuring"
    INCLUDED = "included"  # in the cycle
    SUSPECT = "suspect"  # missed answers: guessed for, not yet lost
    LOST = "lost"  # excluded; its port explored again


class ModuleState(StrEnum):
    """A joint module's own life: configured by the master, then its clock synchronised, then cycling."""

    UNCONFIGURED = "unconfigured"
    SYNCING = "syncing"
    RUNNING = "running"


class Stage(StrEnum):
    """Where a module's exchange of one cycle stands: [A, B] then [C, D] (over SnP-MrT: one query each;
    over RMAP: a write and a read each)."""

    AB = "ab"
    CD = "cd"
    A = "a"
    B = "b"
    C = "c"
    D = "d"
    DONE = "done"


@dataclass(frozen=True)
class CycleConfig:
    period_ns: int = 1_000_000
    phase_ns: int = 0
    # joint j's cycle starts j slots after the period's: a time-slotted schedule (the slides
    # give each joint's [A, B, C, D] 0.05 ms of a six-joint robot's 0.3 ms); 0: all at once
    slot_ns: int = 0
    budget_ns: int = 1_000_000  # [C, D] due this long after the joint's start, [A, B] half as long
    # the management slot: where in the period (after phase_ns) the master sends what is not the
    # cycle (SnP-TSP beacons, exploration probes) and wakes for its own timers, so that neither
    # its trips through its slow path nor the modules' handling of what it sends delay a cycle.
    # Beacons and probes at any phase had cost 1-5% of the exchanges in 2- and 4-joint runs.
    # Here six joints' exchanges end about 0.2 ms into the period (30 us slots) and a beacon
    # costs the master and its module 0.1-0.4 ms of Python: at 0.4 ms both fit before the next
    # period (start late p99 10-14 us with six joints; 29-32 us at 0.3 ms, 22-53 us at 0.6 ms)
    management_ns: int = 400_000
    beacon_ns: int = 10_000_000  # the beacon period modules ask for
    precision_ns: int = 20_000  # the clock precision they ask for
    gain: float = 20.0  # the master's P law for B
    transport: str = "snp"  # or "rmap": the slides' baseline
    rmap_timeout_ns: int = 200_000
    rmap_retries: int = 1

    @property
    def management_grid(self) -> tuple[int, int]:
        """(period, offset) of the management slot on the master's time."""
        return self.period_ns, (self.phase_ns + self.management_ns) % self.period_ns


# --- the master ---------------------------------------------------------------------------------


@dataclass
class Node:
    """A module the master knows of."""

    addr: Any
    info: NodeInfo
    joint: int = -1
    state: NodeState = NodeState.FOUND  # -> CONFIGURING -> INCLUDED -> (SUSPECT) -> LOST
    heard_ns: int = 0
    configured_at: int = 0
    silent_cycles: int = 0
    phase_ns: int = 0  # its cycle's offset in the period (its slot)
    checked: int = -1  # the last of its cycles FDIR looked at


class ArmModel:
    """The master's side of the virtual decomposition: a reference per joint and a chain model.

    B: the desired velocity at T3, v_ref(T3) + K (p_ref(T3) - p(T3)), p extrapolated from the
    module's A.  D: the torque for the module's desired force plus gravity on the links above it,
    which needs every joint's position: a silent module's is guessed.  (Python lists and math:
    for sixteen joints numpy's per-call cost is most of the work.)"""

    def __init__(self, joints: int = 16, gain: float = 20.0, t0: int = 0) -> None:
        self.joints, self.gain, self.t0 = joints, gain, t0
        self.pos, self.vel, self.force = [0.0] * joints, [0.0] * joints, [0.0] * joints
        self.at = [0] * joints  # when pos, vel were measured (master ns)
        self.active = [False] * joints

    def reference(self, joint: int, t_ns: int) -> tuple[float, float]:
        t = (t_ns - self.t0) / 1e9
        w, a = 2 * math.pi * 0.5, 0.2 * (1 + joint / 10)
        return a * math.sin(w * t), a * w * math.cos(w * t)

    def guess(self, joint: int, t_ns: int) -> float:
        """Data obsolescence: the last position, carried on at the last velocity."""
        return self.pos[joint] + self.vel[joint] * (t_ns - self.at[joint]) / 1e9

    def command(self, joint: int, t_ns: int) -> float:
        """B: the desired velocity at t_ns."""
        p_ref, v_ref = self.reference(joint, t_ns)
        return v_ref + self.gain * (p_ref - self.guess(joint, t_ns))

    def torque(self, joint: int, t_ns: int) -> float:
        """D: the joint's desired force, plus gravity on the links from it up (their absolute
        angles: the sums of the joint positions below them)."""
        angle = load = 0.0
        for j in range(self.joints):
            if self.active[j]:
                angle += self.guess(j, t_ns)
                if j >= joint:
                    load += math.cos(angle)
        return 0.8 * self.force[joint] + 2.0 * load

    def known(self, item_id: int) -> bool:
        robot, quantity, joint = split_item_id(item_id)
        ok = quantity in (Quantity.POSITION, Quantity.VELOCITY, Quantity.COMMANDED_VELOCITY, TORQUE, FORCE)
        return robot == ROBOT and joint < self.joints and self.active[joint] and ok

    def refine(self, it: Item) -> None:
        _, quantity, joint = split_item_id(it.id)
        if quantity == Quantity.POSITION:
            self.pos[joint], self.at[joint] = it.value, it.timestamp
        elif quantity == Quantity.VELOCITY:
            self.vel[joint] = it.value
        elif quantity == FORCE:
            self.force[joint] = it.value

    def value(self, item_id: int, t_ns: int) -> float:
        _, quantity, joint = split_item_id(item_id)
        if quantity == Quantity.COMMANDED_VELOCITY:
            return self.command(joint, t_ns)
        if quantity == TORQUE:
            return self.torque(joint, t_ns)
        return float(self.pos[joint] if quantity == Quantity.POSITION else self.vel[joint])


@dataclass(slots=True)
class MasterCounters(Counters):
    guessed: int = 0  # queries answered with a joint's value guessed (its A missed its cycle)
    probes: int = 0
    beacons: int = 0
    included: int = 0  # modules taken into the network
    lost: int = 0  # modules declared lost (FDIR)
    follow_ups: int = 0


class Master:
    """The master node (see the module docstring); `receive` and `poll` return (datagram, addr).

    A master of other cycle messages (cell.modular.cycle: VDC's) gives its model and its own
    `_cycle_query` for the sizes in CYCLE_SIZES."""

    CYCLE_SIZES = frozenset((_A.size, _C.size))  # the datagrams _cycle_query is tried on

    def __init__(
        self,
        ports: list[Any],
        config: CycleConfig,
        clock: Any,
        *,
        explore_ns: int = 20_000_000,
        suspect_cycles: int = 3,
        lost_ns: int = 50_000_000,
        max_joints: int = 16,
        model: ArmModel | None = None,
    ) -> None:
        self.ports, self.config, self.clock = list(ports), config, clock
        self.explore_ns, self.suspect_cycles, self.lost_ns = explore_ns, suspect_cycles, lost_ns
        self.model = model or ArmModel(max_joints, config.gain, clock())
        self.handler = Handler(self.model, clock, service_ns=30_000, margin=1.25, floor_ns=10_000)
        self.beacon_schedule = BeaconSchedule(grid=config.management_grid)
        self.nodes: dict[Any, Node] = {}  # by address
        self.events: deque[tuple[int, str, int, int]] = deque(maxlen=1000)  # (t, what, module, joint)
        self.counters = MasterCounters()
        self._next_explore = 0
        self._a_cycle: dict[int, int] = {}  # joint -> the last cycle its A came in
        self.rmap_target = rmap.Target(MASTER_LA, self._rmap_written)
        self.rmap_init = rmap.Initiator(MASTER_LA, config.rmap_timeout_ns, config.rmap_retries)
        self._rmap_from: Any = None
        self._out: list[tuple[bytes, Any]] = []
        # False while a fast path elsewhere (cell.snp.native.NativeMaster) keeps FDIR's per-cycle
        # watch: poll() and next_due() then leave it out
        self.fdir_here = True

    # --- input ---------------------------------------------------------------------------------

    def receive(self, data: bytes, addr: Any, t_in: int | None = None) -> list[tuple[bytes, Any]]:
        """t_in: when the datagram came in (the kernel's stamp), if not now: the time exchange
        and the admission of queries then do not count how long it waited to be read."""
        now = self.clock() if t_in is None else t_in
        node = self.nodes.get(addr)
        if node is not None:
            node.heard_ns, node.silent_cycles = now, 0
            if node.state == NodeState.SUSPECT:
                node.state = NodeState.INCLUDED
                self.events.append((now, "back", node.info.module_id, node.joint))
            if len(data) in self.CYCLE_SIZES and node.joint >= 0:
                out = self._cycle_query(data, addr, node, now)
                if out is not None:
                    return out
        if rmap.is_rmap(data):
            return self._rmap(data, addr)
        try:
            pkt = decode(data, self.handler._pids)
        except PacketError:
            return self.handler.receive(data, addr)  # counts it and answers as the handler does
        body = pkt.body
        if isinstance(body, NodeInfo):
            return self._found(body, addr, now)
        if isinstance(body, Configured):
            return self._configured(body, addr, now)
        if isinstance(body, TimeSubscribe):
            granted = self.beacon_schedule.subscribe(addr, body.period_ns, now)
            reply = TimeSubscribed(granted, self.beacon_schedule.precision_ns)
            return [(encode(pkt.header.reversed(), reply), addr)]
        if isinstance(body, Query) and node is not None and node.joint >= 0:
            # (a quarter period of slack: the module's servoed clock may run a little ahead)
            self._a_cycle[node.joint] = self._cycle_at(node, now)
        return self.handler.dispatch(pkt, addr, now)

    def _cycle_query(self, data: bytes, addr: Any, node: Node, now: int) -> list[tuple[bytes, Any]] | None:
        """The fast path for a module's A or C: parsed by its shape, its inputs taken, queued with
        the handler (admitted or denied as any query); None if it is anything else (the full
        decoder and handler then deal with it)."""
        model, j = self.model, node.joint
        if not model.active[j]:
            return None
        ids = _IDS[j]
        is_a = len(data) == _A.size
        if is_a:
            f = _A.parse(data)  # ..., qid 8, deadline 9, 2, pos 11-13, vel 14-16, 1, wanted 18-19
            if f is None or f[1] != Pid.MRT or f[11] != ids[0] or f[14] != ids[1] or f[18] != ids[2]:
                return None
            self._a_cycle[j] = self._cycle_at(node, now)
            wanted, t_out, value = ids[2], f[19], model.command
        else:
            f = _C.parse(data)  # ..., qid 8, deadline 9, 1, force 11-13, 1, wanted 15-16
            if f is None or f[1] != Pid.MRT or f[11] != ids[3] or f[15] != ids[4]:
                return None
            wanted, t_out, value = ids[4], f[16], model.torque

        def take() -> None:
            if is_a:
                model.pos[j], model.at[j], model.vel[j] = f[12], f[13], f[15]
            else:
                model.force[j] = f[12]

        return self._queue(f, addr, now, take, self._answer, (wanted, value, j, t_out))

    def _queue(
        self, f: tuple, addr: Any, now: int, take: Callable[[], None], answer: Callable, arg: tuple
    ) -> list:
        """A cycle's query parsed by its shape (f: QueryShape's fields), admitted or denied as any
        query; admitted, its inputs taken (take()) and answer((back, qid, *arg)) queued."""
        h = self.handler
        qid, deadline = f[8], f[9]
        back = Header(f[0], f[1], b"", f[4], f[3])
        h.counters.queries += 1
        if not h.admit(now, deadline):
            return [h.deny(back, qid, addr)]
        take()
        h.enqueue(deadline, answer, (back, qid, *arg), addr, qid, back)
        return []

    @staticmethod
    def _answer(arg: tuple[Header, int, int, Callable[[int, int], float], int, int]) -> bytes:
        """B or D: the wanted item's value (model.command or model.torque) at the wanted time."""
        back, qid, wanted, value, j, t = arg
        return _ANSWER.pack(back.destination, back.pid, back.source_process, back.destination_process, qid,
                            (wanted, value(j, t), t))  # fmt: skip

    def serve(self) -> list[tuple[bytes, Any]]:
        """The pending queries, earliest deadline first."""
        out = []
        while (got := self.handler.serve()) is not None:
            out.append(got)
        return out

    # --- exploration and configuration -------------------------------------------------------

    def _found(self, info: NodeInfo, addr: Any, now: int) -> list[tuple[bytes, Any]]:
        node = self.nodes.get(addr)
        if node is None or node.info.module_id != info.module_id or node.state == NodeState.LOST:
            node = self.nodes[addr] = Node(addr, info, heard_ns=now)
            self.events.append((now, "found", info.module_id, -1))
        node.info = info
        return self._configure_ready(now)

    def _depths(self) -> dict[int, int]:
        """module id -> joint index: its depth in the chain from the base plate (0)."""
        parent = {
            n.info.module_id: n.info.plugged_to for n in self.nodes.values() if n.state != NodeState.LOST
        }
        out: dict[int, int] = {}
        for mid in parent:
            depth, at, seen = 0, mid, set()
            while at in parent and parent[at] != 0 and at not in seen:
                seen.add(at)
                at, depth = parent[at], depth + 1
            if at in parent and parent[at] == 0:
                out[mid] = depth
        return out

    def _configure_ready(self, now: int) -> list[tuple[bytes, Any]]:
        out = []
        depths = self._depths()
        c = self.config
        for n in self.nodes.values():
            if n.state not in (NodeState.FOUND, NodeState.CONFIGURING) or n.info.module_id not in depths:
                continue  # (a module whose chain to the base plate is not known yet waits)
            if n.state == NodeState.CONFIGURING and now - n.configured_at < self.explore_ns:
                continue
            n.joint, n.state, n.configured_at = depths[n.info.module_id], NodeState.CONFIGURING, now
            n.phase_ns = (c.phase_ns + n.joint * c.slot_ns) % c.period_ns
            conf = Configure(n.joint, c.period_ns, n.phase_ns, c.budget_ns, (c.gain,))
            out.append((encode(Header(pid=Pid.MRT), conf), n.addr))
        return out

    def _configured(self, body: Configured, addr: Any, now: int) -> list[tuple[bytes, Any]]:
        node = self.nodes.get(addr)
        if node is None or node.state != NodeState.CONFIGURING or body.joint != node.joint or body.status:
            return []
        node.state = NodeState.INCLUDED
        self.model.active[node.joint] = True
        self.model.at[node.joint] = now
        self._a_cycle.pop(node.joint, None)  # guessed only once it has run (it syncs its clock first)
        node.checked = (now - self.config.budget_ns - node.phase_ns) // self.config.period_ns
        self.counters.included += 1
        self.events.append((now, "included", node.info.module_id, node.joint))
        return []

    # --- timers ---------------------------------------------------------------------------------

    def in_management_slot(self, t: int) -> int:
        """The first management slot at or after t: when slow work due at t should be done."""
        return on_grid(t, self.config.management_grid)

    def _cycle_of(self, t: int) -> int:
        return (t - self.config.phase_ns) // self.config.period_ns

    def _cycle_at(self, node: Node, t: int) -> int:
        """Which of its cycles a module's A coming in at t belongs to (with a quarter period of
        slack: its servoed clock may run a little ahead)."""
        return (t - node.phase_ns + self.config.period_ns // 4) // self.config.period_ns

    def poll(self) -> list[tuple[bytes, Any]]:
        """Exploration probes, RMAP resends, FDIR: call at least once a period (and send the
        beacons due, `beacons()`)."""
        now = self.clock()
        if self.fdir_here:
            self._fdir(now)
        out: list[tuple[bytes, Any]] = []
        if now >= self._next_explore:
            self._next_explore = self.in_management_slot(now + self.explore_ns)
            live = {
                a
                for a, n in self.nodes.items()
                if n.state in (NodeState.INCLUDED, NodeState.SUSPECT, NodeState.CONFIGURING)
            }
            for port in self.ports:
                if port not in live:
                    out.append((encode(Header(pid=Pid.MRT), NodeInfoQuery()), port))
                    self.counters.probes += 1
            out += self._configure_ready(now)
        resend, _failed = self.rmap_init.expire(now)
        out += [(d, self._rmap_addr(d)) for d in resend]
        return out

    def beacons(self) -> Iterator[tuple[bytes, Any]]:
        """The SnP-TSP beacons due, each dated as it is made: send each before taking the next, so
        that it leaves as it is dated (several are often due at once, and a beacon made while
        others wait to be sent carries their encoding and sending in its error)."""
        for addr, seq in self.beacon_schedule.due(self.clock()):
            self.counters.beacons += 1
            yield encode(Header(pid=Pid.TSP), TimeBeacon(seq, self.clock())), addr

    def departed(self, datagram: bytes, t: int) -> list[bytes]:
        """The link's word that a time packet of ours left at t by its kernel's stamp (two-step
        stamping): the TIME_FOLLOW_UP its receiver then wants, for a beacon or a response."""
        fu = follow_up(datagram, t)
        if fu is None:
            return []
        self.counters.follow_ups += 1
        return [fu]

    def next_cycle_start(self, now: int) -> int:
        """The start of the first cycle after now (the modules' A come just after it)."""
        return (self._cycle_of(now) + 1) * self.config.period_ns + self.config.phase_ns

    def next_due(self) -> int:
        """When poll() has something to do next, at the latest."""
        nxt = self._next_explore
        b = self.beacon_schedule.next_due()
        if b is not None:
            nxt = min(nxt, b)
        r = self.rmap_init.next_timeout()
        if r is not None:
            nxt = min(nxt, r)
        c = self.config
        for n in self.nodes.values() if self.fdir_here else ():  # FDIR: each module's next cycle's deadline
            if n.state in (NodeState.INCLUDED, NodeState.SUSPECT):
                nxt = min(nxt, (n.checked + 2) * c.period_ns + n.phase_ns + c.budget_ns)
        return nxt

    def _fdir(self, now: int) -> None:
        """Once per cycle, after its queries' deadline: whose A did not come (guessed), who is
        silent (reported), who is gone (excluded, its port explored again)."""
        c = self.config
        for n in self.nodes.values():
            if n.state not in (NodeState.INCLUDED, NodeState.SUSPECT):
                continue
            cycle = (now - c.budget_ns - n.phase_ns) // c.period_ns  # its last cycle past its deadline
            last = self._a_cycle.get(n.joint)
            if cycle > n.checked and last is not None and last < cycle:
                self.counters.guessed += 1
                n.silent_cycles += 1
                if n.silent_cycles == self.suspect_cycles:
                    n.state = NodeState.SUSPECT
                    self.events.append((now, "silent", n.info.module_id, n.joint))
            n.checked = max(n.checked, cycle)
            if now - n.heard_ns > self.lost_ns:
                self.lose(n, now)

    def lose(self, n: Node, now: int) -> None:
        """Exclude a module gone silent (its port is explored again)."""
        n.state = NodeState.LOST
        self.model.active[n.joint] = False
        self.beacon_schedule.drop(n.addr)
        self.counters.lost += 1
        self.events.append((now, "lost", n.info.module_id, n.joint))

    # --- the RMAP baseline --------------------------------------------------------------------

    def _rmap_addr(self, datagram: bytes) -> Any:
        la = datagram[0]
        return next((n.addr for n in self.nodes.values() if n.joint == la - MODULE_LA0), None)

    def _rmap(self, data: bytes, addr: Any) -> list[tuple[bytes, Any]]:
        if data[2] & 0xC0 == 0:  # a reply to one of our writes
            self.rmap_init.receive(data)
            return []
        self._rmap_from = addr
        self._out = []
        reply = self.rmap_target.receive(data)
        out = [(reply, addr)] if reply is not None else []
        return out + self._out

    def _rmap_written(self, address: int, data: bytes) -> None:
        """A or C landed in our memory: write B or D back to the module."""
        now = self.clock()
        node = self.nodes.get(self._rmap_from)
        if node is None or node.joint < 0 or len(data) != _MSG.size:
            return
        j = node.joint
        x, y, t = _MSG.unpack(data)
        if address == A_BASE + 16 * j:
            self._a_cycle[j] = self._cycle_at(node, now)
            self.model.pos[j], self.model.vel[j], self.model.at[j] = x, y, t
            t3 = t + self.config.period_ns
            b = self.model.value(item(Quantity.COMMANDED_VELOCITY, j), t3)
            _, raw = self.rmap_init.write(MODULE_LA0 + j, B_ADDR, _MSG.pack(b, 0.0, t3), now)
        elif address == C_BASE + 16 * j:
            self.model.force[j] = x
            t6 = t + self.config.period_ns
            d = self.model.value(item(TORQUE, j), t6)
            _, raw = self.rmap_init.write(MODULE_LA0 + j, D_ADDR, _MSG.pack(d, 0.0, t6), now)
        else:
            return
        self._out.append((raw, node.addr))


# --- a joint module ----------------------------------------------------------------------------


@dataclass
class Cycle:
    """One cycle of a module, as it went."""

    scheduled: int  # master ns: its slot on the grid
    start: int  # master ns, T1
    stage: Stage = Stage.AB  # AB -> CD -> DONE (A, B, C, D with RMAP)
    deadline: int = 0
    qid: int = 0
    missed: int = 0  # of its two exchanges, how many were guessed


class JointModule:
    """A joint module (slave); `receive(data, raw)` and `poll(raw)` return datagrams for the master.

    raw is the module's own clock (`cell.snp.tsp.Oscillator`); everything it schedules is on the
    master's time through its servo.  A module of other cycle messages (cell.modular.cycle: VDC's)
    gives the reply shapes it takes (ANSWERS) and its own _start, _second, took_b, took_d, _drive."""

    ANSWERS = {Stage.AB: _ANSWER, Stage.CD: _ANSWER}  # the shape each exchange's answer comes in

    def __init__(
        self,
        module_id: int,
        plugged_to: int,
        port: int = 0,
        *,
        beacon_ns: int = 10_000_000,
        precision_ns: int = 20_000,
        source_process: int = 0,
    ) -> None:
        self.info = NodeInfo(module_id, ModuleKind.JOINT, plugged_to, port)
        self.beacon_ns, self.precision_ns = beacon_ns, precision_ns  # what it asks SnP-TSP for
        self.granted: TimeSubscribed | None = None
        self.source_process = source_process or module_id
        self.servo = ClockServo()
        # two-step SnP-TSP: once the master has followed a time packet up, a beacon or response
        # waits for its follow-up (the time it really left); _BEACON_FOLLOW_UPS_MISSED in a row
        # and the module goes back to the packets' own one-step times
        self.two_step = False
        self.follow_ups = self.unfollowed = 0  # beacons and responses taken with / left without one
        self._beacon: tuple[int, int] | None = None  # (seq, raw at arrival) awaiting its follow-up
        self._response: tuple[TimeResponse, int] | None = None  # (it, raw at arrival) likewise
        self._sent_t1: dict[int, int] = {}  # a request's t1 as stamped -> as it left (its kernel)
        self._missed_follow_ups = 0  # in a row
        self._asked = 0  # 1 + the beacons seen since our TIME_REQUEST went out (0: none out)
        self.config: Configure | None = None
        self.joint = -1
        self.state = ModuleState.UNCONFIGURED  # -> syncing -> running
        self.transport = "snp"
        self.cycle: Cycle | None = None
        self.next_start = 0  # master ns
        # done cycles: (scheduled start, T1, end) master ns, and how many of its exchanges were guessed
        self.cycles: list[tuple[int, int, int, int]] = []
        self.missed = {Stage.AB: 0, Stage.CD: 0}
        self.overruns = 0  # cycles skipped because the last one was still running
        self.late = 0  # answers that came after their exchange was guessed (or to no query of its)
        self.pos = self.vel = 0.0
        self.v_des = self.torque = 0.0
        self._qid = 0
        self._exchanges = 0
        self._raw = 0  # the module's clock at the datagram or poll being handled
        self.rmap_target = rmap.Target(0, self._rmap_written)
        self.rmap_init: rmap.Initiator | None = None
        self._rmap_out: list[bytes] = []

    def _header(self, pid: int) -> Header:
        return Header(0, pid, b"", self.source_process, 0)

    # --- input ---------------------------------------------------------------------------------

    def receive(self, data: bytes, raw: int) -> list[bytes]:
        self._raw = raw
        cy = self.cycle
        shape = self.ANSWERS.get(cy.stage) if cy is not None else None
        f = shape.parse(data) if shape is not None and len(data) == shape.size else None
        if f is not None and f[1] == Pid.MRT and f[8] == cy.qid:  # type: ignore[union-attr]
            return self._answered(f[11::3], raw)  # (the fast path: B or D, by its shape)
        if rmap.is_rmap(data):
            return self._rmap(data, raw)
        try:
            pkt = decode(data)
        except PacketError:
            return []
        body = pkt.body
        if isinstance(body, NodeInfoQuery):
            info = NodeInfo(
                self.info.module_id, self.info.kind, self.info.plugged_to, self.info.port,
                tuple(item(q, max(self.joint, 0)) for q in (Quantity.POSITION, Quantity.VELOCITY, FORCE)),
                self.joint if self.joint >= 0 else 0xFF,
            )  # fmt: skip
            return [encode(pkt.header.reversed(), info)]
        if isinstance(body, Configure):
            return self._configure(body, pkt.header, raw)
        if isinstance(body, TimeBeacon):
            if self.state == ModuleState.UNCONFIGURED:
                return []
            if self.two_step and self._beacon is not None:  # the last one's follow-up never came
                self._unfollowed()  # (after a few: one-step again)
            if self.two_step:
                self._beacon = (body.seq, raw)  # taken when its follow-up comes
            else:
                self._beacon_at(raw, body.t_master)
            return self._exchange_lost()
        if isinstance(body, TimeFollowUp):
            return self._followed_up(body)
        if isinstance(body, TimeSubscribed):
            self.granted = body
            return []
        if isinstance(body, TimeResponse):
            if self.two_step:
                self._response = (body, raw)
                return []
            return self._exchanged(body.t1, body.t2, body.t3, raw)
        if isinstance(body, Reply | Denied):
            if cy is not None and cy.stage != Stage.DONE and body.query_id == cy.qid:
                items = body.items if isinstance(body, Reply) else ()
                return self._answered(tuple(i.value for i in items) or None, raw)
            self.late += 1
        return []

    # --- SnP-TSP -------------------------------------------------------------------------------

    def departed(self, datagram: bytes, t: int) -> list[bytes]:
        """The link's word that a time packet of ours left at t (its kernel's stamp, our clock):
        a request's real departure, kept for its response's follow-up; nothing to send."""
        try:
            body = decode(datagram).body
        except PacketError:
            return []
        if isinstance(body, TimeRequest):
            self._sent_t1[body.t1] = t  # (at most _EXCHANGES, ever)
        return []

    def _followed_up(self, f: TimeFollowUp) -> list[bytes]:
        """A beacon or response waiting for this follow-up is taken with the time it really left."""
        self.two_step, self._missed_follow_ups = True, 0
        if f.of == PacketType.TIME_BEACON and self._beacon is not None and self._beacon[0] == f.ref:
            _, raw = self._beacon
            self._beacon = None
            self.follow_ups += 1
            self._beacon_at(raw, f.t)
        elif f.of == PacketType.TIME_RESPONSE and self._response and self._response[0].t1 == f.ref:
            r, raw = self._response
            self._response = None
            self.follow_ups += 1
            return self._exchanged(self._sent_t1.pop(r.t1, r.t1), r.t2, f.t, raw)
        return []

    def _unfollowed(self) -> None:
        """A beacon whose follow-up did not come (lost): left out; after a few, one-step again."""
        self._beacon = None
        self.unfollowed += 1
        self._missed_follow_ups += 1
        if self._missed_follow_ups >= _BEACON_FOLLOW_UPS_MISSED:
            self.two_step = False
            self._missed_follow_ups = 0

    def _beacon_at(self, raw: int, t_master: int) -> None:
        """A beacon that left the master at t_master came in at raw: the servo; running after three."""
        self.servo.beacon(raw, t_master)
        if self.state == ModuleState.SYNCING and self.servo.samples >= 3:
            self.state = ModuleState.RUNNING
            self._schedule(self.servo.now(raw) + self.config.period_ns)  # type: ignore[union-attr]

    def _exchanged(self, t1: int, t2: int, t3: int, t4: int) -> list[bytes]:
        """A two-way exchange done (t1, t4 ours; t2, t3 the master's): the path delay; a few more."""
        self.servo.exchange(t1, t2, t3, t4)
        self._asked = 0
        return self._request()

    def _request(self) -> list[bytes]:
        """The next TIME_REQUEST, while there are exchanges left (the least queued of 8 gives the
        delay)."""
        if self._exchanges >= _EXCHANGES:
            return []
        self._exchanges += 1
        self._asked = 1
        return [encode(self._header(Pid.TSP), TimeRequest(self._raw))]

    def _exchange_lost(self) -> list[bytes]:
        """At each beacon: a request still unanswered (or its response's follow-up still missing)
        after two beacons was lost on the way; ask again (from the same 8), or the exchanges stop
        there and the delay is whatever the ones done gave (a one-step start: 5-10 us too long)."""
        if not self._asked:
            return []
        self._asked += 1
        if self._asked <= 2:
            return []
        self._response, self._asked = None, 0
        return self._request()

    def _configure(self, c: Configure, header: Header, raw: int) -> list[bytes]:
        first = self.config is None
        self.config, self.joint = c, c.joint
        self.rmap_target.logical_address = MODULE_LA0 + c.joint
        if self.rmap_init is not None:
            self.rmap_init.logical_address = MODULE_LA0 + c.joint
        out = [encode(header.reversed(), Configured(c.joint, 0))]
        # subscribed anew each time: configured again means the master had excluded us, and with
        # us our subscription (or it never had it: a lost TIME_SUBSCRIBE left a module syncing
        # for good, excluded and configured again every 70 ms)
        out.append(encode(self._header(Pid.TSP), TimeSubscribe(self.beacon_ns, self.precision_ns)))
        if first:
            self.state = ModuleState.SYNCING
            out += self._request()
        return out

    def use_transport(self, transport: str, timeout_ns: int = 200_000, retries: int = 1) -> None:
        """ "snp" (time-bounded queries) or "rmap" (the acknowledged-write baseline)."""
        self.transport = transport
        self.rmap_init = rmap.Initiator(MODULE_LA0, timeout_ns, retries) if transport == "rmap" else None

    # --- the cycle ------------------------------------------------------------------------------

    def _schedule(self, after: int) -> None:
        c = self.config
        assert c is not None
        k = -(-(after - c.phase_ns) // c.period_ns)
        self.next_start = k * c.period_ns + c.phase_ns

    def next_wake(self) -> int | None:
        """The raw time poll() has something to do at (a cycle start or a deadline), if any."""
        if self.state != ModuleState.RUNNING:
            return None
        at = self.next_start
        if self.cycle is not None and self.cycle.stage != Stage.DONE:
            at = min(at, self.cycle.deadline)
        if self.rmap_init is not None and (t := self.rmap_init.next_timeout()) is not None:
            return min(self.servo.to_raw(at), t)
        return self.servo.to_raw(at)

    def poll(self, raw: int) -> list[bytes]:
        self._raw = raw
        if self.state != ModuleState.RUNNING:
            return []
        now = self.servo.now(raw)
        out: list[bytes] = []
        cy = self.cycle
        if cy is not None and cy.stage != Stage.DONE and now >= cy.deadline:
            out += self._expired(cy, raw)
        if self.rmap_init is not None:
            resend, failed = self.rmap_init.expire(raw)
            out += resend
            if failed and cy is not None and cy.stage != Stage.DONE:
                out += self._expired(cy, raw)
        if now >= self.next_start:
            if self.cycle is not None and self.cycle.stage != Stage.DONE:
                self.overruns += 1
                self._finish(self.cycle, now)
            out += self._start(self.next_start, raw)
            self._schedule(now + 1)
        return out

    def _start(self, scheduled: int, raw: int) -> list[bytes]:
        c = self.config
        assert c is not None
        t1 = self.servo.now(raw)
        stage = Stage.AB if self.transport == "snp" else Stage.A
        self.cycle = Cycle(scheduled, t1, stage, scheduled + c.budget_ns // 2)
        j = self.joint
        if self.transport == "rmap":
            assert self.rmap_init is not None
            _, dg = self.rmap_init.write(MASTER_LA, A_BASE + 16 * j, _MSG.pack(self.pos, self.vel, t1), raw)
            return [dg]
        ids = _IDS[j]
        a = (ids[0], self.pos, t1, ids[1], self.vel, t1)
        return [self._query(_A, a, (ids[2], t1 + c.period_ns))]

    def _query(self, shape: QueryShape, inputs: tuple, wanted: tuple) -> bytes:
        """A or C: inputs (id, value, timestamp) and the wanted (id, timestamp), flat."""
        cy = self.cycle
        assert cy is not None
        self._qid = qid = (self._qid + 1) & 0xFFFFFFFF
        cy.qid = qid
        return shape.pack(0, Pid.MRT, self.source_process, 0, qid, cy.deadline, inputs, wanted)

    def _answered(self, values: tuple | None, raw: int) -> list[bytes]:
        """The answer to the cycle's query in flight came: its items' values, or None (denied)."""
        cy = self.cycle
        assert cy is not None
        now = self.servo.now(raw)
        if cy.stage == Stage.AB:
            if values is None:
                self._miss(cy, Stage.AB)
            else:
                self.took_b(values)
            return self._second(cy)
        if cy.stage == Stage.CD:
            if values is None:
                self._miss(cy, Stage.CD)
            else:
                self.took_d(values)
            self._finish(cy, now)
        return []

    def took_b(self, values: tuple) -> None:
        self.v_des = values[0]

    def took_d(self, values: tuple) -> None:
        self.torque = values[0]

    def _second(self, cy: Cycle) -> list[bytes]:
        """[C, D] (or the C write): the desired force from the velocity error."""
        c = self.config
        assert c is not None
        force = 5.0 * (self.v_des - self.vel)
        j = self.joint
        cy.deadline = cy.scheduled + c.budget_ns
        if self.transport == "rmap":
            assert self.rmap_init is not None
            cy.stage = Stage.C
            data = _MSG.pack(force, 0.0, cy.start)
            _, dg = self.rmap_init.write(MASTER_LA, C_BASE + 16 * j, data, self._raw)
            return [dg]
        cy.stage = Stage.CD
        ids = _IDS[j]
        return [self._query(_C, (ids[3], force, cy.start), (ids[4], cy.start + c.period_ns))]

    def _expired(self, cy: Cycle, raw: int) -> list[bytes]:
        """Its deadline passed with no answer: guess (the last value) and go on."""
        now = self.servo.now(raw)
        if self.rmap_init is not None:
            self.rmap_init.in_flight.clear()
        if cy.stage in (Stage.AB, Stage.A, Stage.B):
            self._miss(cy, Stage.AB)
            return self._second(cy)
        self._miss(cy, Stage.CD)
        self._finish(cy, now)
        return []

    def _miss(self, cy: Cycle, which: str) -> None:
        self.missed[which] += 1
        cy.missed += 1

    def _finish(self, cy: Cycle, now: int) -> None:
        cy.stage = Stage.DONE
        self.cycles.append((cy.scheduled, cy.start, now, cy.missed))
        self._drive(cy)

    def _drive(self, cy: Cycle) -> None:
        """The cycle's end: the joint driven after what it got (here a fast drive after the desired
        velocity)."""
        assert self.config is not None
        self.vel += (self.v_des - self.vel) * 0.5
        self.pos += self.vel * self.config.period_ns / 1e9

    # --- the RMAP baseline --------------------------------------------------------------------

    def _rmap(self, data: bytes, raw: int) -> list[bytes]:
        cy = self.cycle
        if data[2] & 0xC0 == 0:  # the master acknowledged our A or C
            if self.rmap_init is None or (got := self.rmap_init.receive(data)) is None:
                return []
            if cy is not None and got[1] == rmap.Status.SUCCESS:
                cy.stage = {Stage.A: Stage.B, Stage.C: Stage.D}.get(cy.stage, cy.stage)
            return []
        self._rmap_out = []
        reply = self.rmap_target.receive(data)
        return ([reply] if reply is not None else []) + self._rmap_out

    def _rmap_written(self, address: int, data: bytes) -> None:
        cy = self.cycle
        if cy is None or cy.stage == Stage.DONE or len(data) != _MSG.size:
            return
        value, _, t = _MSG.unpack(data)
        if t != cy.start + self.config.period_ns:  # type: ignore[union-attr]
            return  # an answer to an earlier cycle, retried late: that cycle has been guessed
        if address == B_ADDR and cy.stage in (Stage.A, Stage.B):
            self.v_des = value
            self._rmap_out += self._second(cy)
        elif address == D_ADDR and cy.stage in (Stage.C, Stage.D):
            self.torque = value
            self._finish(cy, self.servo.now(self._raw))
