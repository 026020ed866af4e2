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

The master is cell.snp.master's, a module cell.snp.module's; this module holds what both use (the
items, the states and stages, the cycle's configuration).

A joint module waits to be configured, subscribes to beacons and servos its clock, then
runs its cycle on the master's time grid: [A, B] (its state at T1; the desired velocity at
T3) and [C, D] (its desired force; the torque), each answered before its deadline or
replaced by a guess (no retry).  With transport "rmap" it writes A and C to the master's
memory as acknowledged RMAP writes (fixed timeout, one retry) and is written B and D.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import StrEnum

from cell.snp.packet import (
    Quantity,
    query_shape,
    reply_shape,
)

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
