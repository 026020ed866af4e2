"""The modular robot's master node, sans IO (seed 002; cell.snp.modular has the overview): it
explores its ports, configures the modules, sends their beacons, answers their time-bounded
queries and watches them (FDIR by data obsolescence)."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from cell.counters import Counters
from cell.snp import rmap
from cell.snp.handler import Handler
from cell.snp.modular import (
    _A,
    _ANSWER,
    _C,
    _IDS,
    _MSG,
    A_BASE,
    B_ADDR,
    C_BASE,
    D_ADDR,
    FORCE,
    MASTER_LA,
    MODULE_LA0,
    ROBOT,
    TORQUE,
    CycleConfig,
    NodeState,
    item,
)
from cell.snp.packet import (
    Configure,
    Configured,
    Header,
    Item,
    NodeInfo,
    NodeInfoQuery,
    PacketError,
    Pid,
    Quantity,
    Query,
    TimeBeacon,
    TimeSubscribe,
    TimeSubscribed,
    decode,
    encode,
    follow_up,
    split_item_id,
)
from cell.snp.tsp import BeaconSchedule, on_grid


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
