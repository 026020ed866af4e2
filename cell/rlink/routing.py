"""A Responsive Link node's routing table (the paper's Fig. 6), as dense arrays.

The reference part of an entry is (source, destination, priority); the rest
says whether event packets (EE) and data packets (DE) take the route, whether
the priority is rewritten (PE, to P0/P1) and which links the packet leaves on
(L0, the node's host, to L4: several bits multicast, all five broadcast).
Every (source, destination, priority) has its entry in 256 x 256 x 4 arrays,
so a lookup is one index whatever the table holds; routes given with
wildcards fill many entries at once, later routes over earlier ones, and can
be changed while the node runs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cell.rlink.packet import PRIORITIES, Kind

LINKS = 5  # L0 (the host) .. L4
ALL_LINKS = (1 << LINKS) - 1


@dataclass(frozen=True)
class Route:
    """One routing rule; None in src, dst or priority matches any."""

    links: tuple[int, ...]  # output links, 0..4 (0: deliver to this node's host)
    src: int | None = None
    dst: int | None = None
    priority: int | None = None
    event: bool = True  # EE
    data: bool = True  # DE
    new_priority: int | None = None  # PE set, with P0/P1 = this

    def __post_init__(self) -> None:
        if not self.links or any(not 0 <= link < LINKS for link in self.links):
            raise ValueError(f"links must name 0..{LINKS - 1} (got {self.links})")
        for name, v, top in (("src", self.src, 255), ("dst", self.dst, 255), ("priority", self.priority, 3)):
            if v is not None and not 0 <= v <= top:
                raise ValueError(f"{name} must be 0..{top} or any (got {v})")
        if self.new_priority is not None and not 0 <= self.new_priority < PRIORITIES:
            raise ValueError(f"new_priority must be 0..{PRIORITIES - 1} (got {self.new_priority})")


class RoutingTable:
    def __init__(self, routes: list[Route] | None = None) -> None:
        shape = (256, 256, PRIORITIES)
        self.links = np.zeros((2, *shape), np.uint8)  # per kind: output link bitmap; 0 = no route
        self.rewrite = np.full(shape, -1, np.int8)  # PE: the new priority, -1 = keep
        for route in routes or []:
            self.add(route)

    def add(self, r: Route) -> None:
        """Set the entries r matches (over what was there)."""
        at = tuple(slice(None) if v is None else v for v in (r.src, r.dst, r.priority))
        bitmap = sum(1 << link for link in set(r.links))
        for kind, enabled in ((Kind.EVENT, r.event), (Kind.DATA, r.data)):
            self.links[(kind, *at)] = bitmap if enabled else 0
        self.rewrite[at] = -1 if r.new_priority is None else r.new_priority

    def remove(self, src: int | None = None, dst: int | None = None, priority: int | None = None) -> None:
        at = tuple(slice(None) if v is None else v for v in (src, dst, priority))
        self.links[(slice(None), *at)] = 0
        self.rewrite[at] = -1

    def lookup(self, kind: Kind, src: int, dst: int, priority: int) -> tuple[int, int]:
        """(output link bitmap, priority to leave with); bitmap 0: no route for this kind."""
        p = int(self.rewrite[src, dst, priority])
        return int(self.links[kind, src, dst, priority]), priority if p < 0 else p
