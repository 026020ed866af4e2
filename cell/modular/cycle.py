"""VDC in the running SnP cycle (seed 002): the master's recursions answering the modules' time-bounded
queries, and joint modules driving a MuJoCo arm, between processes on the cycle's time grid.

`cell.snp.modular` runs the SnP cycle (exploration, configuration, SnP-TSP clocks, EDF admission,
FDIR); this module gives it VDC's messages and arithmetic instead of the toy's scalars:
- `VdcMaster`: a module's [A, B] query (q, qd in; B's 20 values wanted, cell.modular.wire's shapes)
  is answered with the forward recursion up to its body; its [C, D] query (F*_r in; tau_r wanted)
  with the backward recursion from the tip in to it.  Both run when the answer is served (earliest
  deadline first), on what has come in by then: a body's A that has not come this cycle is its last
  one carried on at its velocity (data obsolescence), an F*_r that has not come is its last.  In the
  slotted schedule joint j's A comes after those below it, so B's recursion has this cycle's A's;
  D's takes the outboard bodies' F*_r of this cycle where they have come, of the cycle before where
  not (the "[C, D] with the neighbour's force of the cycle before" case of cell.modular.loop).
- `VdcModule`: a joint module whose A is its joint on the `Plant` at T1, whose C is its body's
  required net force from B (cell.modular.vdc.Module), and whose motor gets the torque from D.  A
  missing B is its last extrapolated, a missing D its last held (no retry), as in cell.modular.loop.
- `Plant`: the arm itself, MuJoCo stepped in real time on the host's clock with the torques the
  modules last set; a joint whose module is not running holds on its brake.
"""

from __future__ import annotations

import ctypes
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from cell.modular.arm import ModularArm
from cell.modular.loop import VdcArm
from cell.modular.reference import CYCLE_NS, Reference
from cell.modular.vdc import AXIS, BASE, B, Carry, Gains, Module, carried_force, forward_step
from cell.modular.vdc import A as AMsg
from cell.modular.wire import (
    A_LOCAL_QUERY,
    A_QUERY,
    B_LOCAL_REPLY,
    B_REPLY,
    C_QUERY,
    D_REPLY,
    G_PASS,
    b_of,
    b_values,
    ids_of,
    outboard_ids,
)
from cell.snp.master import ArmModel, Master, Node
from cell.snp.modular import CycleConfig, Stage
from cell.snp.module import Cycle, JointModule
from cell.snp.native import PlantState, VdcModuleState, VdcState, c_addr
from cell.snp.packet import Header, Pid

SETTLE_NS = 500_000_000  # from every joint in the cycle to the reference's start: the clocks settle
SAFE_AFTER = 3  # cycles in a row with a guess in them: a module's joint on its brake (VdcModule._drive)


class Plant:
    """The six-module arm in MuJoCo, in real time: stepped (TIMESTEP a step) up to the clock's now
    with the torques last set (held between cycles, as a motor drive holds its command); a joint
    whose module does not drive it holds on its brake.  Records the tool every 1 ms, the last
    `capacity_s` of them in a ring (`since` reads them).  Its state is in numpy arrays so that the
    modules' C cycle (cell/snp/cycle.c) steps the same arm through them."""

    def __init__(
        self, q0: np.ndarray, clock: Callable[[], int] = time.monotonic_ns, capacity_s: float = 120.0
    ) -> None:
        self.arm = arm = ModularArm(q0)
        n = arm.dof
        self.clock = clock
        self.dt_ns, self.period_ns = round(arm.model.opt.timestep * 1e9), CYCLE_NS  # (its records')
        self.brake = (VdcArm.BRAKE_KP, VdcArm.BRAKE_KD)
        now = clock()
        self.time = np.array([now, now, 0], dtype=np.int64)  # t, the next record's time, records made
        self.tau = np.zeros(n)
        self.driven = np.zeros(n, dtype=np.int64)
        self.hold = np.asarray(q0, dtype=np.float64).copy()  # where each brake holds its joint
        self.limit = np.array([b.torque_max for b in arm.bodies])
        cap = int(capacity_s * 1e9 / CYCLE_NS)
        self.rec_t = np.zeros(cap, dtype=np.int64)
        self.rec_tool = np.zeros((cap, 3))

    def module_for(self, slot: Any) -> VdcModule:
        """The module a runner's slot plugs in to drive its joint of this arm (cell.snp.runner.Slot:
        its ids, cd, adapt and believed)."""
        return VdcModule(
            slot.module_id, slot.plugged_to, self, port=1, cd=slot.cd,
            gains=Gains(adapt=slot.adapt), believed=slot.believed,
        )  # fmt: skip

    @property
    def records(self) -> list[tuple[int, np.ndarray]]:
        """(host ns, the tool's position) every 1 ms, as far back as the ring holds."""
        return self.since(0)[1]

    def since(self, n: int) -> tuple[int, list[tuple[int, np.ndarray]]]:
        """The records from the n-th made on (those the ring still holds), and how many are made."""
        made, cap = int(self.time[2]), len(self.rec_t)
        idx = [i % cap for i in range(max(n, made - cap), made)]
        return made, list(zip(self.rec_t[idx].tolist(), self.rec_tool[idx], strict=True))

    def advance(self) -> None:
        data, tool, t = self.arm.data, self.arm.tool, self.time
        now = self.clock()
        while t[0] + self.dt_ns <= now:
            tau = self.tau.copy()
            idle = self.driven == 0
            if idle.any():
                brake = self.brake[0] * (self.hold - data.qpos) - self.brake[1] * data.qvel
                tau[idle] = np.clip(brake, -self.limit, self.limit)[idle]
            self.arm.step(tau, 1)
            t[0] += self.dt_ns
            if t[0] >= t[1]:
                i = t[2] % len(self.rec_t)
                self.rec_t[i], self.rec_tool[i] = t[0], data.site_xpos[tool]
                t[2] += 1
                t[1] += self.period_ns

    def joint(self, j: int) -> tuple[float, float]:
        """Joint j's position and velocity now."""
        self.advance()
        d = self.arm.data
        return float(d.qpos[j]), float(d.qvel[j])

    def drive(self, j: int, tau: float) -> None:
        self.advance()
        self.tau[j], self.driven[j] = tau, 1

    def release(self, j: int) -> None:
        """Its module gone: the joint on its brake where it stands."""
        self.advance()
        self.driven[j], self.hold[j] = 0, self.arm.data.qpos[j]


class VdcModel(ArmModel):
    """The master's VDC: the forward recursion (B) and the backward one (D) over the joints' last
    messages; the reference starts SETTLE_NS after every joint is in the cycle (start_ns)."""

    def __init__(self, reference: Reference, gains: Gains | None = None, period_ns: int = CYCLE_NS) -> None:
        self.bodies = ModularArm().bodies
        n = len(self.bodies)
        super().__init__(n, 0.0, 0)
        self.gains, self.period_ns = gains or Gains(), period_ns  # (the cycle's)
        self.followed = reference  # the reference it follows (ArmModel.reference: the toy's, unused)
        self.start_ns: int | None = None  # (None: SETTLE_NS after every joint is in the cycle)
        self.generation = 0  # references followed (a C master takes the new one)
        self.f_star = [np.zeros(6) for _ in range(n)]
        self.seq = [0] * n  # A's taken per joint: what a cached step of the recursion was made from
        # the recursion, per body: (its cycle and the A's it was made from, its B, transform, carry)
        self._chain: list[tuple[tuple[int, ...], B, np.ndarray, Carry] | None] = [None] * n

    def follow(self, reference: Reference, start_ns: int) -> None:
        """Track `reference` from master time start_ns (its first point until then, its last after)."""
        self.followed, self.start_ns = reference, start_ns
        self.generation += 1

    def take_a(self, j: int, q: float, qd: float, t: int) -> None:
        self.pos[j], self.vel[j], self.at[j] = q, qd, t
        self.seq[j] += 1

    def desired(self, j: int, t: int) -> tuple[float, float, float]:
        """The reference's position, velocity and acceleration of joint j at t (its start pose
        until it starts, its end pose after)."""
        ref = self.followed
        if self.start_ns is None and all(self.active):
            self.start_ns = t + SETTLE_NS
        k = 0 if self.start_ns is None else int(np.clip((t - self.start_ns) // CYCLE_NS, 0, len(ref.t) - 1))
        return float(ref.q[k, j]), float(ref.qd[k, j]), float(ref.qdd[k, j])

    def b(self, j: int, t: int) -> B:
        """Joint j's B at t (its T1): the recursion from the base, each body from its last A carried
        on to t.  The steps below j made this cycle from the same A's are taken as they are (in the
        slotted schedule: each body once a cycle)."""
        cycle = (t + self.period_ns // 2) // self.period_ns
        start = j  # (the step after the highest one below j made this cycle from the same A's)
        while start > 0 and ((c := self._chain[start - 1]) is None or c[0] != (cycle, *self.seq[:start])):
            start -= 1
        below = self._chain[start - 1] if start > 0 else None  # (made: the loop above stopped there)
        carry = BASE if below is None else below[3]
        lam = self.gains.lam
        for i in range(start, j + 1):  # (a module gone: its joint on its brake where it was)
            a = AMsg(self.guess(i, t), self.vel[i]) if self.active[i] else AMsg(self.pos[i], 0.0)
            out, x, carry = forward_step(self.bodies[i], lam, a, *self.desired(i, t), carry)
            self._chain[i] = ((cycle, *self.seq[: i + 1]), out, x, carry)
        return out  # (joint j's: the loop's last)

    def _transform(self, i: int) -> np.ndarray:
        """Body i's ^iX_{i-1} as its last B's recursion made it."""
        c = self._chain[i]
        return c[2] if c is not None else self.bodies[i].transform(self.pos[i])

    def rot(self, i: int) -> np.ndarray:
        """Body i's axes in its parent's (R = rot rz(q)) as _transform has them."""
        return self._transform(i)[:3, :3].T

    def outboard(self, j: int) -> np.ndarray:
        """G: what the bodies out from j to the tip need of body j, in j's frame (their F*_r as
        last taken, carried in)."""
        n = len(self.bodies)
        if j == n - 1:
            return np.zeros(6)
        f = self.f_star[n - 1]
        for i in range(n - 2, j, -1):
            f = self.f_star[i] + carried_force(self._transform(i + 1), f)
        return carried_force(self._transform(j + 1), f)

    def tau_r(self, j: int) -> float:
        """Joint j's D: its body's F*_r plus what the bodies out to the tip need of it."""
        return float(AXIS @ (self.f_star[j] + self.outboard(j)))

    # --- its C state (cell.snp.native.NativeMaster runs VDC's master in C through these) ---------

    def to_c(self) -> VdcState:
        """VDC's master in C: each body's items, place and force (the reference: reference_to_c)."""
        v = VdcState(ref_dt_ns=CYCLE_NS, settle_ns=SETTLE_NS, lam=self.gains.lam)
        for j, body in enumerate(self.bodies):
            _, b_ids, f_ids, _ = ids_of(j)
            v.b_ids[j][:], v.f_ids[j][:], v.g_ids[j][:] = b_ids, f_ids, outboard_ids(j)
            v.body_pos[j][:], v.body_rot[j][:] = body.pos, body.rot.ravel()
            v.rot[j][:] = self.rot(j).ravel()
            v.f_star[j][:] = self.f_star[j]
            v.key_cycle[j] = -1
        return v

    def reference_to_c(self, v: VdcState) -> list[np.ndarray]:
        """The reference it follows, and its start, into C; the arrays C reads (where numpy holds
        them: the caller keeps them alive)."""
        ref = self.followed
        arrays = [np.ascontiguousarray(a, dtype=np.float64) for a in (ref.q, ref.qd, ref.qdd)]
        v.n_ref, v.start_ns = len(ref.t), self.start_ns or 0
        v.q_ref, v.qd_ref, v.qdd_ref = (a.ctypes.data for a in arrays)
        return arrays

    def from_c(self, v: VdcState) -> None:
        """What C did: when the reference started, and the forces."""
        self.start_ns = v.start_ns or None
        self.f_star = [np.array(f) for f in v.f_star]


class VdcMaster(Master):
    """The SnP master with VDC's cycle messages (cell.modular.wire's shapes) and arithmetic.  A
    module's [A, B] in the local shape (A_LOCAL_QUERY: it computes its own [C, D]) brings its last
    F*_r and is answered with B and G (VdcModel.outboard); its placement is the module's choice."""

    KINDS = {A_QUERY.size: "a", C_QUERY.size: "c", A_LOCAL_QUERY.size: "local"}  # a cycle query's, by size
    CYCLE_SIZES = frozenset(KINDS)

    def __init__(
        self, ports: list[Any], config: CycleConfig, clock: Any, reference: Reference, **kw: Any
    ) -> None:
        self.vdc = VdcModel(reference, period_ns=config.period_ns)
        super().__init__(ports, config, clock, model=self.vdc, **kw)
        self.ids = [ids_of(j) for j in range(len(self.vdc.bodies))]
        self.g_ids = [outboard_ids(j) for j in range(len(self.vdc.bodies))]

    def _cycle_query(self, data: bytes, addr: Any, node: Node, now: int) -> list[tuple[bytes, Any]] | None:
        model, j = self.vdc, node.joint
        if j >= len(self.ids) or not model.active[j]:
            return None
        a_ids, b_ids, f_ids, tau = self.ids[j]
        kind = self.KINDS[len(data)]
        if kind == "c":
            f = C_QUERY.parse(data)  # ..., qid 8, deadline 9, 6, F* 11-28, 1, wanted 30-31
            if f is None or f[1] != Pid.MRT or f[11:29:3] != f_ids or f[30] != tau:
                return None
        else:  # ..., qid 8, deadline 9, n, q 11-13, qd 14-16, [F* 17-34,] m, wanted B's (and G's)
            f = (A_QUERY if kind == "a" else A_LOCAL_QUERY).parse(data)
            if f is None or f[1] != Pid.MRT or f[11] != a_ids[0] or f[14] != a_ids[1]:
                return None
            if kind == "local" and (f[17:35:3] != f_ids or f[36] != b_ids[0] or f[76] != self.g_ids[j][0]):
                return None
            if kind == "a" and f[18] != b_ids[0]:
                return None
            self._a_cycle[j] = self._cycle_at(node, now)

        def take() -> None:
            if kind != "c":
                model.take_a(j, f[12], f[15], f[13])
            if kind != "a":
                model.f_star[j] = np.array(f[12:30:3] if kind == "c" else f[18:36:3])

        return self._queue(f, addr, now, take, self._vdc_answer, (j, f[13], kind))

    def _vdc_answer(self, arg: tuple[Header, int, int, int, str]) -> bytes:
        back, qid, j, t, kind = arg
        _, b_ids, _, tau = self.ids[j]
        head = (back.destination, back.pid, back.source_process, back.destination_process, qid)
        if kind == "c":
            return D_REPLY.pack(*head, (tau, self.vdc.tau_r(j), t))
        values = b_values(self.vdc.b(j, t))
        if kind == "local":
            ids, values = b_ids + self.g_ids[j], [*values, *self.vdc.outboard(j)]
            return B_LOCAL_REPLY.pack(
                *head, tuple(x for k, v in zip(ids, values, strict=True) for x in (k, v, t))
            )
        return B_REPLY.pack(*head, tuple(x for k, v in zip(b_ids, values, strict=True) for x in (k, v, t)))


class VdcModule(JointModule):
    """A joint module of the modular arm: its joint read from and its motor driven on the plant.

    cd, who computes its [C, D]:
    - "master": the master, from the C it sends (a second query);
    - "local" (the slides' "locally"): its cycle is one query, [A, B] with its last F*_r beside A,
      answered with B and G (what the bodies outboard of it need of its body, from their F*_r of
      the cycle before); its D is its F*_r plus G projected on its axis;
    - "neighbour": the same query, then it waits for G of this cycle from its outboard neighbour
      (G_PASS; the master's G its guess if it has not come by the deadline) and passes its own
      force, carried into its inboard neighbour's frame, on to that one (`to_inboard`): the chain
      from the tip in, one message a module.  A G of this cycle that comes before B (its
      neighbour ahead of it) is kept for when it waits; one of another cycle is counted late, one
      with another joint's items refused."""

    def __init__(
        self,
        module_id: int,
        plugged_to: int,
        plant: Plant,
        port: int = 0,
        *,
        cd: str = "master",
        gains: Gains | None = None,
        believed: float = 1.0,
        **kw: Any,
    ) -> None:
        """gains: VDC's (Gains.adapt > 0: its body's inertial parameters adapted as it runs);
        believed: what it takes its body's inertia to be, as a share of the true one."""
        super().__init__(module_id, plugged_to, port, **kw)
        if cd not in ("master", "local", "neighbour"):
            raise ValueError(f'cd: "master", "local" or "neighbour" (got {cd!r})')
        self.plant, self.gains, self.cd, self.believed = plant, gains or Gains(), cd, believed
        self.local = cd != "master"  # (it asks the local way: one query, its F*_r in, B and G out)
        self.ANSWERS = {Stage.AB: B_LOCAL_REPLY if self.local else B_REPLY, Stage.CD: D_REPLY}
        if cd == "neighbour":
            self.ANSWERS[Stage.CD] = G_PASS
        self.to_inboard: list[bytes] = []  # neighbour: its force for its inboard neighbour, to send
        self.g_early: tuple[int, tuple] | None = None  # neighbour: (cycle, G) come before it waited
        self.refused = 0  # neighbour: G_PASSes with another joint's items
        self.module: Module | None = None  # its body's dynamics, once it knows its joint (dynamics())
        self._module_joint = -1
        self.b: B | None = None  # the last B it took
        self.b_fresh = False  # (this cycle's)
        self.g = np.zeros(6)  # local: the last G it took
        self.f_star = np.zeros(6)  # local: its last F*_r (sent with the next A)
        self.tau_r = 0.0
        self.q = self.qd = 0.0  # its joint's position and velocity at this cycle's T1
        self.missed_run = 0  # cycles in a row with a guessed exchange
        self.braked = 0  # times it went on its brake for them

    def _start(self, scheduled: int, raw: int) -> list[bytes]:
        c = self.config
        assert c is not None
        j = self.joint
        self.dynamics()
        t1 = self.servo.now(raw)
        self.cycle = Cycle(scheduled, t1, Stage.AB, scheduled + c.budget_ns // 2)
        self.b_fresh = False
        (pos, vel), b_ids, f_ids, _ = ids_of(j)
        self.q, self.qd = self.plant.joint(j)
        a = (pos, self.q, t1, vel, self.qd, t1)
        if self.local:
            self.cycle.deadline = scheduled + c.budget_ns  # (its one exchange)
            f = tuple(x for k, v in zip(f_ids, self.f_star, strict=True) for x in (k, float(v), t1))
            wanted = tuple(x for k in (*b_ids, *outboard_ids(j)) for x in (k, t1))
            return [self._query(A_LOCAL_QUERY, a + f, wanted)]
        return [self._query(A_QUERY, a, tuple(x for k in b_ids for x in (k, t1)))]

    def dynamics(self) -> Module:
        """Its body's dynamics (its inertia as it believes it, adapted as it runs), made anew only
        when its joint changes."""
        body = self.plant.arm.bodies[self.joint]
        if self.module is None or self._module_joint != self.joint:
            self.module = Module(replace(body, inertia=body.inertia * self.believed), self.gains)
            self._module_joint = self.joint
        return self.module

    def took_b(self, values: tuple) -> None:
        self.b, self.b_fresh = b_of(values[:20]), True
        if self.local:
            self.g = np.array(values[20:26])

    def receive(self, data: bytes, raw: int) -> list[bytes]:
        cy = self.cycle
        if self.cd == "neighbour" and len(data) == G_PASS.size and (f := G_PASS.parse(data)) is not None:
            if f[10::3][:6] != outboard_ids(self.joint):
                self.refused += 1
            elif cy is not None and cy.stage == Stage.CD and f[8] == cy.qid:
                return super().receive(data, raw)
            elif cy is not None and cy.stage == Stage.AB and f[8] == self._cycle_no(cy):
                self.g_early = (f[8], f[11::3][:6])  # (its neighbour ahead of it: kept until it waits)
            else:
                self.late += 1
            return []
        return super().receive(data, raw)

    def took_d(self, values: tuple) -> None:
        if self.cd == "neighbour":  # (its outboard neighbour's G of this cycle)
            self.g = np.array(values[:6])
        else:
            self.tau_r = values[0]

    def _cycle_no(self, cy: Cycle) -> int:
        assert self.config is not None
        return (cy.scheduled // self.config.period_ns) & 0xFFFFFFFF

    def _pass_in(self, cy: Cycle) -> None:
        """neighbour: D from F*_r and G (the neighbour's, or the master's guess), and its force
        carried into its inboard neighbour's frame, for that one (none from the base's)."""
        f = self.f_star + self.g
        self.tau_r = float(AXIS @ f)
        j = self.joint
        if j == 0:
            return
        carried = carried_force(self.plant.arm.bodies[j].transform(self.q), f)
        assert self.config is not None  # (configured: it runs cycles)
        ids, t = outboard_ids(j - 1), self._cycle_no(cy) * self.config.period_ns
        items = tuple(x for k, v in zip(ids, carried, strict=True) for x in (k, float(v), t))
        self.to_inboard.append(G_PASS.pack(0, Pid.MRT, self.source_process, 0, self._cycle_no(cy), items))

    def _second(self, cy: Cycle) -> list[bytes]:
        """[C, D]: its body's required net force from B (its last carried on if this cycle's did not
        come); none before its first B (its joint stays on the brake).  Local: D from it and G here,
        and the cycle ends."""
        c = self.config
        assert c is not None and self.module is not None
        cy.deadline = cy.scheduled + c.budget_ns
        if self.b is None:
            self._finish(cy, cy.start)
            return []
        dt = c.period_ns / 1e9
        if not self.b_fresh:
            p = self.b
            self.b = B(p.qd_r + p.qdd_r * dt, p.qdd_r, p.v_r + p.a_r * dt, p.a_r, p.v)
        # (the inertial parameters adapt on a B that came only: a guessed one's V_r runs on while its
        # V stands, and a stall's error is no measure of them)
        force = self.module.net_force(self.b, dt if self.b_fresh else 0.0).f_star
        if self.cd == "neighbour" and self.joint < self.plant.arm.dof - 1:  # (the tip's G is 0)
            self.f_star = force
            cy.stage, cy.qid = Stage.CD, self._cycle_no(cy)  # (G_PASS's query id: the cycle's number)
            early, self.g_early = self.g_early, None
            return self._answered(early[1], self._raw) if early is not None and early[0] == cy.qid else []
        if self.local:
            self.f_star, self.tau_r = force, float(AXIS @ (force + self.g))
            self._finish(cy, self.servo.now(self._raw))
            return []
        cy.stage = Stage.CD
        _, _, f_ids, tau = ids_of(self.joint)
        inputs = tuple(x for k, v in zip(f_ids, force, strict=True) for x in (k, float(v), cy.start))
        return [self._query(C_QUERY, inputs, (tau, cy.start))]

    def _drive(self, cy: Cycle) -> None:
        """Its motor gets the torque: the chain's share (D, or the last) and its own.  After
        SAFE_AFTER cycles in a row with a guess in them its joint goes on its brake where it stands,
        until a whole cycle comes (fail safe: guesses carried on that long had driven a starved arm
        unstable)."""
        if self.cd == "neighbour" and self.b is not None:
            self._pass_in(cy)
        self.missed_run = self.missed_run + 1 if cy.missed else 0
        if self.missed_run >= SAFE_AFTER:
            if self.plant.driven[self.joint]:
                self.plant.release(self.joint)
                self.braked += 1
        elif self.b is not None and self.module is not None:
            self.plant.drive(self.joint, self.module.torque(self.tau_r, self.b, self.qd))

    # --- its C state (cell.snp.native.NativeCycles runs its cycle in C through these) ----------

    def to_c(self, plant: PlantState, inboard: Any = None) -> VdcModuleState:
        """Its VDC in C: its body's inertia and gains, its item ids, the plant, who computes its
        [C, D] (a neighbour: where its inboard one is)."""
        module, g = self.dynamics(), self.gains
        body = module.body  # (its inertia as the module believes it)
        mass = body.inertia[5, 5]
        _, b_ids, f_ids, _ = ids_of(self.joint)
        v = VdcModuleState(
            joint=self.joint, joint_gain=g.joint * body.torque_max / 150.0, armature=body.armature,
            damping=body.damping, torque_max=body.torque_max, plant=ctypes.pointer(plant),
        )  # fmt: skip
        v.b_ids[:], v.f_ids[:], v.inertia[:] = b_ids, f_ids, body.inertia.ravel()
        v.local, v.g_ids[:], v.g[:], v.f_star[:] = self.local, outboard_ids(self.joint), self.g, self.f_star
        v.adapt, v.theta[:], v.bound[:], v.mass0 = g.adapt, module.theta, module.bound, module.mass0
        v.neighbour, v.tip, v.q = self.cd == "neighbour", self.joint == self.plant.arm.dof - 1, self.q
        v.body_pos[:], v.body_rot[:] = body.pos, body.rot.ravel()
        if inboard is not None and self.joint > 0:
            (v.nb_ip, v.nb_port), v.g_in_ids[:] = c_addr(inboard), outboard_ids(self.joint - 1)
        v.k[:] = (*[g.body_rot * mass] * 3, *[g.body_lin * mass] * 3)
        if self.b is not None:
            v.b[:], v.have_b = b_values(self.b), 1
        v.tau_r, v.safe_after, v.missed_run, v.braked = self.tau_r, SAFE_AFTER, self.missed_run, self.braked
        return v

    def from_c(self, v: VdcModuleState) -> None:
        """Its VDC's state as C has it: its cycle goes on in Python from there."""
        self.missed_run, self.braked, self.tau_r, self.q, self.qd = v.missed_run, v.braked, v.tau_r, v.q, v.qd
        self.b = b_of(v.b) if v.have_b else None
        assert self.module is not None  # (to_c made it)
        self.g, self.f_star, self.module.theta = np.array(v.g), np.array(v.f_star), np.array(v.theta)


def tool_error_mm(
    records: list[tuple[int, np.ndarray]], reference: Reference, start_ns: int | None
) -> np.ndarray:
    """The tool's error (mm) against the reference's, each ms a plant recorded (Plant.records) while
    the reference ran from start_ns (none: it never started)."""
    if not records or start_ns is None:
        return np.zeros(0)
    t = np.array([r[0] for r in records], dtype=np.int64)
    tool = np.array([r[1] for r in records])
    k = (t - start_ns) // CYCLE_NS
    keep = (k >= 0) & (k < len(reference.t))
    return np.linalg.norm(tool[keep] - reference.tool[k[keep]], axis=1) * 1e3
