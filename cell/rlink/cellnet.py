"""The cell's Responsive Link network, from [rlink]: three nodes in a star, their ports and routes.

    dataplane (D) --L1-- L1 hub (H) L2 --L1-- robots (R)
                           | L0: the host interface (cell estop, task scripts, skill servers)

Addresses come from the config; 255 is every node.  Ports are consecutive
from [rlink] port: the hub's host interface, then each link's event and data
sockets on both ends.  Every route is derived here, once, so that the three
processes agree (`cell rlink routes` prints them).
"""

from __future__ import annotations

from dataclasses import dataclass

from cell.config import RlinkConfig
from cell.rlink.link import LinkPorts
from cell.rlink.routing import Route, RoutingTable

BROADCAST = 255
ROLES = ("hub", "dataplane", "robots")
# port offsets from [rlink] port
HOST = 0
_HUB_L1, _DP_L1, _HUB_L2, _RB_L1 = 1, 3, 5, 7  # each: event, then data at +1
PORTS = 9


@dataclass(frozen=True)
class Topology:
    config: RlinkConfig

    def address(self, role: str) -> int:
        return int(getattr(self.config, role))

    def _at(self, offset: int) -> tuple[str, int]:
        return self.config.host, self.config.port + offset

    @property
    def host(self) -> tuple[str, int]:
        """The hub's host interface: where local processes send events and hear the hub's host."""
        return self._at(HOST)

    def links(self, role: str) -> list[LinkPorts]:
        pair = {"dataplane": (_HUB_L1, _DP_L1), "robots": (_HUB_L2, _RB_L1)}
        if role == "hub":
            return [
                LinkPorts(n, self._at(mine), self._at(mine + 1), self._at(peer), self._at(peer + 1))
                for n, (mine, peer) in ((1, pair["dataplane"]), (2, pair["robots"]))
            ]
        hub_end, mine = pair[role]
        return [LinkPorts(1, self._at(mine), self._at(mine + 1), self._at(hub_end), self._at(hub_end + 1))]

    def routes(self, role: str) -> list[Route]:
        me = self.address(role)
        if role == "hub":
            return [
                Route(links=(0,), dst=me),
                Route(links=(1,), dst=self.address("dataplane")),
                Route(links=(2,), dst=self.address("robots")),
                Route(links=(0, 1, 2), dst=BROADCAST),
            ]
        # a leaf: everything goes up to the hub, but what is for this node (or every node) comes in
        return [Route(links=(1,)), Route(links=(0,), dst=me), Route(links=(0, 1), dst=BROADCAST)]

    def table(self, role: str) -> RoutingTable:
        if role not in ROLES:
            raise ValueError(f"a cell node is one of {ROLES} (got {role!r})")
        return RoutingTable(self.routes(role))
