"""A cell node whose host owns robots (the data plane's, the robots'): the IO around a Station.

Events in on the node's own sockets become the Station's orders, handed to
apply(); a task runs the beacon watchdog; counters() gives the station's and
the links' figures.  Subclasses say which node they are (`role`) and what an
order does.
"""

from __future__ import annotations

import asyncio
import time

from cell.config import CellConfig
from cell.rlink.cellnet import Topology
from cell.rlink.link import NodeLink, link_counters
from cell.rlink.node import Node
from cell.rlink.packet import Packet
from cell.rlink.station import Order, Station


class LeafNode:
    role = ""  # "dataplane" or "robots"

    def __init__(self, config: CellConfig, robots: set[int]) -> None:
        topo = Topology(config.rlink)
        self.hub = topo.address("hub")
        self.station = Station(robots, int(config.rlink.watchdog_s * 1e9))
        node = Node(topo.address(self.role), topo.table(self.role))
        self.link = NodeLink(node, topo.links(self.role), self.on_event)
        self.watchdog_s = config.rlink.watchdog_s

    def close(self) -> None:
        self.link.close()

    def restore(self, robots: list[int], emergency: list[bool]) -> None:
        """Robots the hub holds stopped (rlink.held) while this node was away (a restart): stopped here
        too, as the orders it missed would have, until a resume names them."""
        for em in (True, False):
            mine = [r for r, e in zip(robots, emergency, strict=True) if e == em and r in self.station.robots]
            if mine:
                self.apply(self.station.stop(mine, em))

    def on_event(self, p: Packet) -> None:
        order = self.station.on_event(p, time.monotonic_ns())
        if order is not None:
            self.apply(order)

    def apply(self, order: Order) -> None:
        raise NotImplementedError

    async def run(self) -> None:
        async with asyncio.TaskGroup() as tg:
            tg.create_task(self.link.run(), name="rlink")
            if self.watchdog_s:
                tg.create_task(self._watch(), name="rlink-watchdog")

    async def _watch(self) -> None:
        while True:
            await asyncio.sleep(self.watchdog_s / 4)
            order = self.station.check(time.monotonic_ns())
            if order is not None:
                self.apply(order)

    def counters(self) -> dict[str, float]:
        out: dict[str, float] = {f"rlink.{k}": v for k, v in self.station.as_dict().items()}
        out.update(link_counters(self.link))
        return out
