"""The hub of the cell's Responsive Link (cell.rlink.cellnet): routes events between its host
interface (L0: `cell estop`, task scripts, skill servers), the data plane's node (L1) and the
robots' node (L2), sends the watchdog beacon, and tells the bus after the fact (events/robot/<name>).
Served by services/rlink.py.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass

from cell.bus import Bus
from cell.config import CellConfig
from cell.counters import Counters
from cell.rlink import events
from cell.rlink.cellnet import BROADCAST, Topology
from cell.rlink.events import EventError, Reason, RobotState
from cell.rlink.link import NodeLink, link_counters
from cell.rlink.node import Node
from cell.rlink.packet import EventType, Kind, Packet
from cell.v1 import robot_pb2

RE = robot_pb2.RobotEvent
_ORDERS = {EventType.ESTOP: RE.KIND_ESTOP, EventType.STOP: RE.KIND_STOP}
_STATES = {RobotState.STILL: RE.KIND_STILL, RobotState.RESUMED: RE.KIND_RESUME}


@dataclass(slots=True)
class HubCounters(Counters):
    orders: int = 0  # stop/resume orders sent to the robots
    reports: int = 0  # robots' state reports received
    beacons: int = 0
    bad_events: int = 0  # events the hub could not take (unknown robot, bad payload)


class Hub:
    def __init__(self, config: CellConfig, bus: Bus | None = None) -> None:
        topo = Topology(config.rlink)
        self.config, self.bus = config, bus
        self.address = topo.address("hub")
        self.names = {r.id: r.name for r in config.robots}
        node = Node(self.address, topo.table("hub"))
        self.link = NodeLink(node, topo.links("hub"), self.on_event, host=topo.host)
        self.stopped: dict[int, str] = {}  # robot -> why, as the robots report it
        # robot -> e-stop (True) or stop: ordered through the hub, not yet released by a resume (a node
        # that restarts, the data plane's, asks for it: rlink.held)
        self.held: dict[int, bool] = {}
        self.counters = HubCounters()

    def close(self) -> None:
        self.link.close()

    def on_event(self, p: Packet) -> None:
        """Everything addressed to the hub's host (and every broadcast) passes here."""
        if p.src == self.address and p.type == EventType.BEACON:
            return
        try:
            if p.type in (EventType.ESTOP, EventType.STOP, EventType.RESUME, EventType.START):
                self.counters.orders += 1
                named = events.decode_set(p.payload).ids(self.names.keys())
                for rid in named:
                    if p.type == EventType.RESUME:
                        self.held.pop(rid, None)
                    elif p.type in _ORDERS:  # (an e-stop outranks a stop)
                        self.held[rid] = self.held.get(rid, False) or p.type == EventType.ESTOP
                if p.type in _ORDERS:
                    for rid in named:
                        self._tell(rid, _ORDERS[EventType(p.type)], f"{EventType(p.type).name} ordered")
            elif p.type == EventType.STATE:
                self.counters.reports += 1
                rep = events.decode_state(p.payload)
                if rep.state in (RobotState.STOPPING, RobotState.STILL):
                    self.stopped[rep.robot] = rep.reason.name.lower()
                    if rep.state == RobotState.STOPPING and rep.reason == Reason.WATCHDOG:
                        self._tell(rep.robot, RE.KIND_ESTOP, "the Responsive Link's beacon was lost")
                elif rep.state == RobotState.RESUMED:
                    self.stopped.pop(rep.robot, None)
                if rep.state in _STATES:
                    text = f"{rep.state.name.lower()} ({rep.reason.name.lower()})"
                    if rep.state == RobotState.STILL:
                        text += f" {rep.detail / 1e3:.1f} ms after the stop"
                    self._tell(rep.robot, _STATES[rep.state], text)
        except EventError:
            self.counters.bad_events += 1

    def held_reply(self, _req: robot_pb2.HeldRequest | None = None) -> robot_pb2.HeldReply:
        ids = sorted(self.held)
        return robot_pb2.HeldReply(robot_ids=ids, emergency=[self.held[r] for r in ids])

    def _tell(self, robot: int, kind: RE.Kind, text: str) -> None:
        name = self.names.get(robot)
        if self.bus is None or name is None:
            return
        ev = RE(robot_id=robot, name=name, kind=kind, text=text, t_ns=time.monotonic_ns())
        self.bus.publish(f"events/robot/{name}", ev)

    async def beacon(self) -> None:
        hz = self.config.rlink.beacon_hz
        if not hz:
            return
        period_ns = round(1e9 / hz)
        next_ns = time.monotonic_ns()
        while True:
            now = time.monotonic_ns()
            self.link.send(Kind.EVENT, BROADCAST, EventType.BEACON, events.encode_beacon(now), priority=1)
            self.counters.beacons += 1
            next_ns += period_ns
            await asyncio.sleep(max(0.0, (next_ns - time.monotonic_ns()) / 1e9))

    def report(self) -> dict[str, float]:
        out = self.counters.as_dict("rlink.")
        out["rlink.stopped"] = len(self.stopped)
        out["rlink.clients"] = len(self.link.clients)
        out.update(link_counters(self.link))
        return out
