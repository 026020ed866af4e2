"""The SpW-SnP-MR demonstrator: a master and one slave process per joint, 1 kHz, over SnP-MrT.

Every cycle each slave (a joint module) asks the master two time-bounded
queries, as in the proposal's A/B/C/D exchange:

- [A, B]: "my position and velocity at T1 are these (A); what is my desired
  velocity at T3 (B)?"  The master answers from the reference trajectory and
  the slave's state (a P law).
- [C, D]: "my desired force is this (C); what torque (D)?"  The master
  answers from its model of the arm (here: a gain and gravity term).

A query not answered by its deadline (denied, or nothing came) is not
retried: the slave uses a guessed value (the last one, extrapolated) and
counts the miss (failure handling by data obsolescence).  Item ids extend the
cell's: quantity 5 = joint torque (N m), 6 = desired force (N) for a joint
module, robot 0 = the modular robot.
"""

from __future__ import annotations

import asyncio
import math
import time
from typing import Any

import numpy as np

from cell.snp.client import DeadlineMissed, QueryDenied, SnpClient
from cell.snp.endpoint import HandlerEndpoint
from cell.snp.handler import Handler
from cell.snp.packet import Item, Quantity, split_item_id

ROBOT = 0
TORQUE, FORCE = 5, 6
PERIOD_NS = 1_000_000


def item(quantity: int, joint: int) -> int:
    return (ROBOT << 16) | (quantity << 8) | joint


class MasterModel:
    """The master's side: what the slaves' queries ask for (a StateSource for the handler)."""

    def __init__(self, joints: int, gain: float = 20.0) -> None:
        self.joints, self.gain = joints, gain
        self.pos = np.zeros(joints)
        self.vel = np.zeros(joints)
        self.force = np.zeros(joints)
        self.t0 = time.time_ns()

    def reference(self, joint: int, t_ns: int) -> tuple[float, float]:
        """A slow sine per joint: position and velocity."""
        t = (t_ns - self.t0) / 1e9
        w = 2 * math.pi * 0.5
        a = 0.2 * (1 + joint / 10)
        return a * math.sin(w * t), a * w * math.cos(w * t)

    def known(self, item_id: int) -> bool:
        robot, quantity, joint = split_item_id(item_id)
        ok_q = quantity in (Quantity.POSITION, Quantity.VELOCITY, Quantity.COMMANDED_VELOCITY, TORQUE, FORCE)
        return robot == ROBOT and joint < self.joints and ok_q

    def refine(self, it: Item) -> None:
        _, quantity, joint = split_item_id(it.id)
        if quantity == Quantity.POSITION:
            self.pos[joint] = it.value
        elif quantity == Quantity.VELOCITY:
            self.vel[joint] = it.value
        elif quantity == FORCE:
            self.force[joint] = it.value

    def value(self, item_id: int, t_ns: int) -> float:
        _, quantity, joint = split_item_id(item_id)
        if quantity == Quantity.COMMANDED_VELOCITY:  # the desired velocity at t
            p_ref, v_ref = self.reference(joint, t_ns)
            return v_ref + self.gain * (p_ref - self.pos[joint])
        if quantity == TORQUE:
            return 0.8 * self.force[joint] + 2.0 * math.cos(self.pos[joint])  # a gain and gravity
        return float(self.pos[joint] if quantity == Quantity.POSITION else self.vel[joint])


async def run_master(joints: int, port_out: Any, stop: Any) -> dict[str, float]:
    handler = Handler(MasterModel(joints), time.time_ns, service_ns=30_000)  # type: ignore[arg-type]
    loop = asyncio.get_running_loop()
    endpoint = HandlerEndpoint(handler)
    transport, _ = await loop.create_datagram_endpoint(lambda: endpoint, local_addr=("127.0.0.1", 0))
    port_out.put(transport.get_extra_info("sockname")[1])
    await asyncio.to_thread(stop.wait)
    transport.close()
    return dict(handler.counters)


async def run_slave(joint: int, port: int, seconds: float, budget_ns: int) -> dict[str, Any]:
    """One joint module: 1 kHz, two queries a cycle, guesses on a miss; its cycle times."""
    from cell.timer import PeriodicTimer

    pos = vel = 0.0
    v_des = torque = 0.0
    cycles: list[int] = []
    misses = {"ab": 0, "cd": 0}
    async with SnpClient(("127.0.0.1", port), source_process=joint + 1) as snp:
        offset, delay = await snp.sync_time(rounds=16)  # one host: the true offset is 0
        start = time.monotonic_ns() + 50_000_000
        start -= start % PERIOD_NS
        timer = PeriodicTimer(start, PERIOD_NS)
        n = int(seconds * 1e9 / PERIOD_NS)
        try:
            for _ in range(n):
                await timer.wait()
                t1 = snp.now()
                deadline, t3 = t1 + budget_ns, t1 + PERIOD_NS
                a = [
                    Item(item(Quantity.POSITION, joint), pos, t1),
                    Item(item(Quantity.VELOCITY, joint), vel, t1),
                ]
                b = item(Quantity.COMMANDED_VELOCITY, joint)
                try:
                    v_des = (await snp.query([(b, t3)], a, deadline))[b].value
                except (QueryDenied, DeadlineMissed):
                    misses["ab"] += 1  # keep the last desired velocity (extrapolated: constant)
                c = [Item(item(FORCE, joint), 5.0 * (v_des - vel), t1)]
                d = item(TORQUE, joint)
                try:
                    torque = (await snp.query([(d, t3)], c, deadline))[d].value
                except (QueryDenied, DeadlineMissed):
                    misses["cd"] += 1
                cycles.append(snp.now() - t1)
                # the joint: its velocity follows the desired one (a fast drive); torque is reported
                vel += (v_des - vel) * 0.5
                pos += vel * PERIOD_NS / 1e9
        finally:
            timer.close()
    return {"cycles": cycles, "misses": misses, "torque": torque, "offset_ns": offset, "delay_ns": delay}
