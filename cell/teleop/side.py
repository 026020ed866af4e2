"""One side of the bilateral experiment, sans IO: its arm, its controller, its state, its trace.

A side is driven one control period at a time: `tick(peer)` takes the newest
sample the peer's data packets brought (or None), measures the arm, computes
the command with the Fig. 14 law, runs the physics for one period and returns
the sample to send.  When the loop woke late, `tick(peer, periods=n)` first
lets the world run the n - 1 periods it missed under the command it held (as
a real drive would), then acts.  Events (START, STOP, RESUME, ESTOP, MODE)
change the state at once, whatever the data link is doing.  The same object
runs in the real-time processes (cell.teleop.realtime) and in the lockstep
runner (cell.teleop.lockstep).
"""

from __future__ import annotations

import numpy as np

from cell.rlink.packet import EventType
from cell.teleop import law
from cell.teleop.law import Gains, Mode
from cell.teleop.model import Arm, ObjectSpec
from cell.teleop.operator import Operator
from cell.teleop.wire import Role, Sample, State

PERIOD_S = 0.001  # the paper's sampling time
STEPS = 2  # physics steps per period (model.TIMESTEP = 0.5 ms)
STALE_PERIODS = 250  # peer data older than this (ms): the side stops and holds where it is
COLUMNS = (
    "t", "x", "z", "vx", "vz", "fx", "fz", "ux", "uz", "q1", "q2",
    "peer_fz", "peer_z", "peer_age", "state", "hand_z", "deflection",
)  # fmt: skip


class Trace:
    """Every period's figures, in preallocated columns (the loop does not allocate)."""

    def __init__(self, capacity: int) -> None:
        self.data = np.full((capacity, len(COLUMNS)), np.nan)
        self.n = 0
        self.col = {c: i for i, c in enumerate(COLUMNS)}

    def add(self, row: list[float]) -> None:
        if self.n < len(self.data):
            self.data[self.n] = row
            self.n += 1

    def __getitem__(self, name: str) -> np.ndarray:
        return self.data[: self.n, self.col[name]]

    def since(self, start: int) -> np.ndarray:
        return self.data[start : self.n]


class Side:
    def __init__(
        self,
        role: Role,
        obj: ObjectSpec | None = None,
        gains: Gains | None = None,
        operator: Operator | None = None,
        coulomb_nm: float = 0.0,
        capacity: int = 120_000,
    ) -> None:
        if role == Role.LOCAL and operator is None:
            raise ValueError("the local side needs an operator")
        self.role = role
        self.arm = Arm(obj if role == Role.REMOTE else None, coulomb_nm)
        self.gains = gains or Gains()
        self.operator = operator
        self.state = State.IDLE
        self.mode = Mode.MODIFIED
        self.tick_no = 0
        self.trace = Trace(capacity)
        self.hold_at = self.arm.tip().x.copy()
        self.peer: Sample | None = None  # the newest sample heard
        self.events: list[tuple[int, str]] = []  # (tick, what) for the log
        self.stale = 0  # periods run on data older than STALE_PERIODS

    # --- events ------------------------------------------------------------------------------

    def event(self, type: int, payload: bytes = b"") -> State:
        """A state change from the event link; returns the state it leaves the side in."""
        before = self.state
        if type == EventType.ESTOP:
            self.state = State.ESTOPPED
        elif type == EventType.STOP and self.state == State.RUNNING:
            self.state = State.STOPPED
        elif type in (EventType.START, EventType.RESUME) and self.state != State.RUNNING:
            self.state = State.RUNNING
        elif type == EventType.MODE and payload:
            self.mode = Mode(payload[0])
            self.events.append((self.tick_no, f"mode {self.mode.name.lower()}"))
        if self.state != before:
            self.hold_at = self.arm.tip().x.copy()
            self.events.append((self.tick_no, f"{before.name.lower()} -> {self.state.name.lower()}"))
        return self.state

    # --- the period ----------------------------------------------------------------------------

    def tick(self, peer: Sample | None, periods: int = 1, sent_ns: int = 0) -> Sample:
        for _ in range(periods - 1):  # missed periods: the world goes on under the held command
            self._world()
            self.tick_no += 1
        if peer is not None and (self.peer is None or peer.tick >= self.peer.tick):
            self.peer = peer
        arm = self.arm
        s = arm.tip()
        u = self._command(s.x, s.v, s.f)
        arm.drive(u)
        peer = self.peer
        age = self.tick_no - peer.tick if peer is not None else -1
        q = arm.data.qpos
        self.trace.add([
            self.tick_no * PERIOD_S, s.x[0], s.x[1], s.v[0], s.v[1], s.f[0], s.f[1], u[0], u[1], q[0], q[1],
            peer.f[1] if peer is not None else np.nan, peer.x[1] if peer is not None else np.nan,
            age, float(self.state),
            self.operator.hand[1] if self.operator is not None else np.nan, arm.object_deflection(),
        ])  # fmt: skip
        out = Sample(sent_ns, self.tick_no, int(self.state), int(self.mode), s.x, s.v, s.f)
        self._world()
        self.tick_no += 1
        return out

    def _world(self) -> None:
        """One period of the physical world: the operator's hand acts, the arm moves."""
        if self.operator is not None:
            s = self.arm.tip()
            self.arm.hand = self.operator.force(self.tick_no * PERIOD_S, PERIOD_S, s.x, s.v)
        self.arm.step(STEPS)

    def _command(self, x: np.ndarray, v: np.ndarray, f: np.ndarray) -> np.ndarray:
        g, peer = self.gains, self.peer
        if self.state == State.ESTOPPED:  # the brakes hold where the arm was: whatever pushes on it
            return law.hold_force(g, x, v, self.hold_at, brake=True)
        if self.state == State.RUNNING and (peer is None or self.tick_no - peer.tick > STALE_PERIODS):
            self.stale += 1
            if peer is not None:  # it did speak, and went quiet: stop (None: not started yet, wait)
                self.state = State.STOPPED
                self.hold_at = x.copy()
                self.events.append((self.tick_no, "running -> stopped (peer data stale)"))
        if self.state != State.RUNNING or peer is None or peer.state == State.ESTOPPED:
            return law.hold_force(g, x, v, self.hold_at)
        if self.role == Role.LOCAL:
            return law.local_force(g, self.mode, v, f, peer.f)
        return law.remote_force(g, self.mode, x, v, f, peer.x, peer.v, peer.f)
