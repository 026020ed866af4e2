"""A joint module of the modular robot, sans IO (seed 002; cell.snp.modular has the overview): it is
configured, servos its clock to the master's beacons and runs its cycle on the master's grid."""

from __future__ import annotations

from dataclasses import dataclass

from cell.snp import rmap
from cell.snp.modular import (
    _A,
    _ANSWER,
    _BEACON_FOLLOW_UPS_MISSED,
    _C,
    _EXCHANGES,
    _IDS,
    _MSG,
    A_BASE,
    B_ADDR,
    C_BASE,
    D_ADDR,
    FORCE,
    MASTER_LA,
    MODULE_LA0,
    ModuleState,
    Stage,
    item,
)
from cell.snp.packet import (
    Configure,
    Configured,
    Denied,
    Header,
    ModuleKind,
    NodeInfo,
    NodeInfoQuery,
    PacketError,
    PacketType,
    Pid,
    Quantity,
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
)
from cell.snp.tsp import ClockServo


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
        if f is not None and cy is not None and f[1] == Pid.MRT and f[8] == cy.qid:  # (f: cy's shape)
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
            assert self.config is not None  # (syncing: configured)
            self._schedule(self.servo.now(raw) + self.config.period_ns)

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

    def _miss(self, cy: Cycle, which: Stage) -> None:
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
        assert self.config is not None  # (a cycle: configured)
        if t != cy.start + self.config.period_ns:
            return  # an answer to an earlier cycle, retried late: that cycle has been guessed
        if address == B_ADDR and cy.stage in (Stage.A, Stage.B):
            self.v_des = value
            self._rmap_out += self._second(cy)
        elif address == D_ADDR and cy.stage in (Stage.C, Stage.D):
            self.torque = value
            self._finish(cy, self.servo.now(self._raw))
