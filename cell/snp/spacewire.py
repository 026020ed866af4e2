"""A SpaceWire-style routed network, sans IO: what seed 002's modular robot assumes under SnP-MrT.

Addressing as ECSS-E-ST-50-12C's routers do it, on a packet's leading byte:
- 0: the router's own configuration port: it answers an RMAP read of its identity (who it is, its
  ports, which are up, and the port the read came in by: SpaceWire-PnP's "return port") out of the
  port the read came in by, then along the read's reply address, so that an explorer that does not
  know yet which port of a router it reached it by still hears it (`Explorer`);
- 1..31: path addressing: the router sends the packet out of that port, the byte deleted;
- 32..254: logical addressing: the routing table names the port(s), the byte kept; with several,
  the first whose link is up (group adaptive routing: a network-layer redundancy);
- 255: reserved, dropped.
A packet's end is its EOP, or an EEP when the link it was crossing failed: routers and nodes
discard EEP-ended packets.  SpaceWire has no hop count; a misrouted packet would circulate until a
router's packet timeout spilled it: here a packet that has crossed MAX_HOPS routers is dropped and
counted as a loop.  Nothing a peer sends makes a router raise: every drop is counted by reason.

`Network` joins routers and end nodes with links that go down and up, delivers a packet hop by
hop (each hop HOP_NS); `Explorer` finds the topology from one node by path addresses alone, as
the running master does through the routers (cell.snp.routed.explore_routers), and `explore()` runs
it on a `Network`.  `Redundant` keeps two different paths to a destination and moves to
the other after FAILOVER_CYCLES cycles in a row without an answer over the first (the slides' FDIR:
no retry; a miss is guessed, a run of misses is a permanent failure).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import IntEnum, StrEnum

from cell.counters import Counters, tally
from cell.snp import rmap
from cell.snp.packet import Header, Pid, Query, Reply, decode, encode

CONFIG_PORT = 0
MAX_PATH_PORT = 31
RESERVED = 255
MAX_HOPS = 16
HOP_NS = 2_000  # a router's forwarding plus a link's transfer of a short packet (100 Mbit/s)
FAILOVER_CYCLES = 3  # answers missed in a row over a path before it counts as failed
IDENTITY_ADDR, IDENTITY_LEN = 0, 8  # a router's identity in its configuration port's memory (RMAP)
ROUTER_LA = 0xFE  # the logical address a configuration port answers to (SpaceWire's default)
_IDENTITY = (0, IDENTITY_ADDR, IDENTITY_LEN)  # a read of it: (extended address, address, length)


class End(IntEnum):
    EOP = 0
    EEP = 1


class Drop(StrEnum):
    EMPTY = "empty"
    EEP = "eep"
    LOOP = "loop"
    BAD_PORT = "bad_port"  # a path address beyond the router's ports
    LINK_DOWN = "link_down"  # the port's link (every port of the group) is down
    NO_ROUTE = "no_route"  # a logical address the routing table does not hold
    RESERVED = "reserved"
    BAD_CONFIG = "bad_config"  # at the configuration port: not an RMAP read of the identity


@dataclass(frozen=True)
class Packet:
    data: bytes
    end: End = End.EOP
    hops: int = 0


@dataclass(slots=True)
class RouterCounters(Counters):
    forwarded: int = 0
    config: int = 0
    dropped: dict[str, int] = tally(keys=tuple(d.value for d in Drop))


class Router:
    """One router: `ports` numbered 1..ports, a routing table of logical addresses."""

    def __init__(self, router_id: int, ports: int, table: dict[int, tuple[int, ...]] | None = None) -> None:
        if not 1 <= ports <= MAX_PATH_PORT:
            raise ValueError(f"a router has 1..{MAX_PATH_PORT} ports (got {ports})")
        self.id = router_id
        self.ports = ports
        self.table = dict(table or {})
        self.up = set(range(1, ports + 1))
        self.counters = RouterCounters()

    def _drop(self, why: Drop) -> list[tuple[int, Packet]]:
        self.counters.dropped[why.value] += 1
        return []

    def route(self, pkt: Packet) -> list[tuple[int, Packet]]:
        """Where the packet goes: [(port, packet)] (port 0: this router's configuration port), or []
        dropped (counted)."""
        if not pkt.data:
            return self._drop(Drop.EMPTY)
        if pkt.end == End.EEP:
            return self._drop(Drop.EEP)
        if pkt.hops >= MAX_HOPS:
            return self._drop(Drop.LOOP)
        first = pkt.data[0]
        if first == CONFIG_PORT:  # (answered by configure(), which counts it)
            return [(CONFIG_PORT, Packet(pkt.data[1:], pkt.end, pkt.hops + 1))]
        if first <= MAX_PATH_PORT:
            if first > self.ports:
                return self._drop(Drop.BAD_PORT)
            if first not in self.up:
                return self._drop(Drop.LINK_DOWN)
            self.counters.forwarded += 1
            return [(first, Packet(pkt.data[1:], pkt.end, pkt.hops + 1))]
        if first == RESERVED:
            return self._drop(Drop.RESERVED)
        group = self.table.get(first)
        if not group:
            return self._drop(Drop.NO_ROUTE)
        for port in group:
            if port in self.up:
                self.counters.forwarded += 1
                return [(port, Packet(pkt.data, pkt.end, pkt.hops + 1))]
        return self._drop(Drop.LINK_DOWN)

    def identity(self, return_port: int) -> bytes:
        """What the configuration port answers: b"R", its id, its port count, the port the read came
        in by, a bit per port up."""
        mask = sum(1 << p for p in self.up)
        return b"R" + bytes([self.id & 0xFF, self.ports, return_port]) + mask.to_bytes(4, "big")

    def configure(self, data: bytes, in_port: int) -> list[tuple[int, Packet]]:
        """A packet at the configuration port (its path spent) that came in by in_port: an RMAP read
        of the identity is answered out of in_port, its reply address leading on from the router
        there (see the module docstring); anything else is dropped, counted."""
        try:
            cmd = rmap.decode(data)
        except rmap.RmapError:
            return self._drop(Drop.BAD_CONFIG)
        if not isinstance(cmd, rmap.Read) or (cmd.extended, cmd.address, cmd.length) != _IDENTITY:
            return self._drop(Drop.BAD_CONFIG)
        self.counters.config += 1
        reply = rmap.ReadReply(cmd.initiator, cmd.target, cmd.transaction, self.identity(in_port))
        return [(in_port, Packet(cmd.reply_address.lstrip(b"\x00") + rmap.encode_read_reply(reply)))]


@dataclass(frozen=True)
class RouterInfo:
    """A router's identity as its configuration port gives it."""

    id: int
    ports: int
    return_port: int  # the port the read came in by: the way back to the asker
    up: frozenset[int]


def parse_identity(data: bytes) -> RouterInfo | None:
    """A router's identity; None for anything else."""
    if len(data) != IDENTITY_LEN or data[:1] != b"R":
        return None
    mask = int.from_bytes(data[4:8], "big")
    return RouterInfo(data[1], data[2], data[3], frozenset(p for p in range(1, data[2] + 1) if mask >> p & 1))


@dataclass
class Node:
    """An end node (the master, a module): one or more ports, its identity."""

    name: str
    ports: int = 1
    inbox: list[tuple[int, Packet]] = field(default_factory=list)  # (port, packet) delivered

    def identity(self) -> bytes:
        return b"N" + self.name.encode()


@dataclass
class Delivery:
    node: str
    port: int
    packet: Packet
    ns: int  # its way's time


class Network:
    """Routers and nodes joined by links; packets delivered hop by hop."""

    def __init__(self) -> None:
        self.routers: dict[str, Router] = {}
        self.nodes: dict[str, Node] = {}
        self.links: dict[tuple[str, int], tuple[str, int]] = {}  # both directions
        self.down: set[frozenset[tuple[str, int]]] = set()

    def add_router(self, name: str, router: Router) -> Router:
        self.routers[name] = router
        return router

    def add_node(self, node: Node) -> Node:
        self.nodes[node.name] = node
        return node

    def link(self, a: tuple[str, int], b: tuple[str, int]) -> None:
        self.links[a], self.links[b] = b, a

    def set_link(self, a: tuple[str, int], up: bool) -> None:
        """A link down (both ends see it: their routers' ports go down) or back up."""
        b = self.links[a]
        key = frozenset((a, b))
        (self.down.discard if up else self.down.add)(key)
        for name, port in (a, b):
            if name in self.routers:
                (self.routers[name].up.add if up else self.routers[name].up.discard)(port)

    def send(self, node: str, port: int, data: bytes) -> list[Delivery]:
        """A node sends data out of one of its ports: where it arrived (a router's configuration
        port's answer included: Router.configure)."""
        out: list[Delivery] = []
        queue: deque[tuple[tuple[str, int], Packet, int]] = deque([((node, port), Packet(data), 0)])
        while queue:
            (here, at), pkt, ns = queue.popleft()
            there = self.links.get((here, at))
            if there is None or frozenset(((here, at), there)) in self.down:
                continue  # (nothing there, or a link down: what was on it is lost)
            name, in_port = there
            ns += HOP_NS
            if name in self.nodes:
                if pkt.end == End.EOP:
                    self.nodes[name].inbox.append((in_port, pkt))
                    out.append(Delivery(name, in_port, pkt, ns))
                continue
            router = self.routers[name]
            for out_port, fwd in router.route(pkt):
                if out_port == CONFIG_PORT:
                    out.append(Delivery(name, CONFIG_PORT, fwd, ns))
                    queue += [((name, p), answer, ns) for p, answer in router.configure(fwd.data, in_port)]
                else:
                    queue.append(((name, out_port), fwd, ns))
        return out


class Explorer:
    """The network beyond one of a node's ports, found by path addresses alone (sans IO), breadth
    first: each round reads the identity at the configuration port of whatever is at the end of
    each path (`probes`), takes the answers (`answer`) and, its time up (`timeout`), goes through
    the ports up of each router found, but the one it was reached by, a router met again by another
    path not twice.  A probe's reply address is the way back from the router before its path's
    last hop: the routers' return ports, innermost first.  A path no router answered at ends at a
    node (`ends`; a node does not take a router's configuration read: it drops it)."""

    def __init__(self, initiator: int = 0xFE, max_depth: int = 8) -> None:
        self.initiator, self.max_depth = initiator, max_depth
        self.routers: dict[tuple[int, ...], RouterInfo] = {}
        self.ends: list[tuple[int, ...]] = []
        self.stray = 0  # answers that were no probe's of this round
        self._round: list[tuple[int, ...]] = [()]
        self._asked: dict[int, tuple[int, ...]] = {}  # transaction id: its path, this round
        self._ids: set[int] = set()
        self._tid = 0
        self._depth = 0

    @property
    def done(self) -> bool:
        return not self._round

    @property
    def pending(self) -> int:
        """This round's probes not answered yet."""
        return len(self._asked)

    def probes(self) -> list[bytes]:
        """This round's packets, each from the node's port: path, configuration port, RMAP read."""
        out = []
        for path in self._round:
            self._tid = (self._tid + 1) & 0xFFFF
            self._asked[self._tid] = path
            back = bytes(self.routers[path[:k]].return_port for k in range(len(path) - 1, -1, -1))
            read = rmap.Read(
                ROUTER_LA, self.initiator, self._tid, IDENTITY_ADDR, IDENTITY_LEN,
                reply_address=back.rjust(-(-len(back) // 4) * 4, b"\x00"),
            )  # fmt: skip
            out.append(bytes(path) + bytes([CONFIG_PORT]) + rmap.encode_read(read))
        return out

    def answer(self, data: bytes) -> bool:
        """A datagram that came back to the node: True if it answered a probe of this round."""
        try:
            reply = rmap.decode(data)
        except rmap.RmapError:
            reply = None
        path = self._asked.pop(reply.transaction, None) if isinstance(reply, rmap.ReadReply) else None
        info = parse_identity(reply.data) if path is not None and isinstance(reply, rmap.ReadReply) else None
        if path is None or info is None:
            self.stray += 1
            return False
        self.routers[path] = info
        return True

    def timeout(self) -> None:
        """This round is over: what went unanswered ends at a node; the next round is set."""
        self.ends += [p for p in self._asked.values() if p]
        answered = [p for p in self._round if p in self.routers]
        self._asked.clear()
        self._depth += 1
        self._round = []
        for path in answered:
            info = self.routers[path]
            if info.id in self._ids or self._depth >= self.max_depth:
                continue
            self._ids.add(info.id)
            self._round += [(*path, p) for p in sorted(info.up - {info.return_port})]


def explore(net: Network, node: str, port: int = 1, max_depth: int = 8) -> dict[tuple[int, ...], str]:
    """Explorer on a Network from `node`'s port: every path to what is there, "router N" or
    "node NAME" (the node a probe reached, as the network delivered it)."""
    ex = Explorer(max_depth=max_depth)
    reached: dict[tuple[int, ...], str] = {}
    while not ex.done:
        for probe in ex.probes():
            for d in net.send(node, port, probe):
                if d.node == node:
                    ex.answer(d.packet.data)
                elif d.port != CONFIG_PORT:
                    reached[tuple(probe[: probe.index(CONFIG_PORT)])] = f"node {d.node}"
        ex.timeout()
    found = {path: f"router {info.id}" for path, info in ex.routers.items()}
    return found | {path: reached.get(path, "nothing") for path in ex.ends}


Route = tuple[int, bytes]  # a node's port, and the path address bytes from there


@dataclass
class Redundant:
    """Two different routes to one destination; the first until FAILOVER_CYCLES answers in a row are
    missed over it, then the other (each miss meanwhile guessed, not retried)."""

    routes: tuple[Route, Route]
    active: int = 0
    missed: int = 0
    failovers: int = 0

    @property
    def route(self) -> Route:
        return self.routes[self.active]

    def answered(self, ok: bool) -> bool:
        """A cycle's outcome over the active path; True when it now moved to the other."""
        if ok:
            self.missed = 0
            return False
        self.missed += 1
        if self.missed < FAILOVER_CYCLES:
            return False
        self.active, self.missed = 1 - self.active, 0
        self.failovers += 1
        return True


def ring(modules: Iterable[str]) -> tuple[Network, dict[str, tuple[Route, Route]]]:
    """The demonstrator's network with single redundancy: the master and every module on two
    routers (R1 by port 1, R2 by port 2 of each node); the two routes from the master to each
    module, one through each router."""
    net = Network()
    names = list(modules)
    net.add_node(Node("master", ports=2))
    r1 = net.add_router("R1", Router(1, 1 + len(names)))
    r2 = net.add_router("R2", Router(2, 1 + len(names)))
    net.link(("master", 1), ("R1", 1))
    net.link(("master", 2), ("R2", 1))
    paths = {}
    for k, name in enumerate(names):
        net.add_node(Node(name, ports=2))
        net.link((name, 1), ("R1", 2 + k))
        net.link((name, 2), ("R2", 2 + k))
        r1.table[0x20 + k] = (2 + k,)
        r2.table[0x20 + k] = (2 + k,)
        paths[name] = ((1, bytes([2 + k])), (2, bytes([2 + k])))
    return net, paths


def failover_ms(fail_at_cycle: int = 10, cycles: int = 40, cycle_ns: int = 1_000_000) -> float:
    """Time from a permanent failure of the link between R1 and module m1 to the master's first
    cycle answered again (over R2).  Each cycle one SnP-MrT query goes out over the active route
    with the way back from the router as its return address, and m1 answers along that return
    address; FDIR as Redundant's."""
    net, routes = ring(["m1", "m2"])
    way = Redundant(routes["m1"])
    for k in range(cycles):
        if k == fail_at_cycle:
            net.set_link(("R1", 2), False)
        port, path = way.route
        query = encode(Header(0x20, Pid.MRT, bytes([1]), 1, 2), Query(k, 0))
        there = [d for d in net.send("master", port, path + query) if d.node == "m1"]
        ok = False
        if there:
            asked = decode(there[0].packet.data)
            answer = routed_reply(asked.header, encode(asked.header.reversed(), Reply(k)))
            ok = any(d.node == "master" for d in net.send("m1", there[0].port, answer))
        if k >= fail_at_cycle and ok:
            return (k - fail_at_cycle) * cycle_ns / 1e6 + 2 * there[0].ns / 1e6
        way.answered(ok)
    return float("nan")


def routed_reply(request: Header, reply: bytes) -> bytes:
    """A reply's packet on a routed network: the request's return address leads it back."""
    return bytes(request.return_address) + reply


def cd_cycle_us(where: str, modules: int = 6) -> float:
    """One VDC cycle's critical path on the demonstrator's network (ring(), every message a real
    delivery through R1), for where [C, D] is computed (cell.modular.vdc's WHERE_*): the master's
    (A, B, C and D in turn: D needs every C), the modules' along the chain (A, B, then each module's
    force to its inner neighbour, from the tip in), or each module's alone (A, B; its neighbour's
    force of the cycle before).  Computing time is left out: what the network adds."""
    names = [f"m{k + 1}" for k in range(modules)]
    net, _ = ring(names)

    def one_way(src: str, dst_port_on_r1: int) -> int:
        got = net.send(src, 1, bytes([dst_port_on_r1]) + b"x")
        return max(d.ns for d in got)

    to_master = max(one_way(m, 1) for m in names)  # A (or C): the slowest module's
    to_module = max(one_way("master", 2 + k) for k in range(modules))  # B (or D)
    ns = to_master + to_module
    if where == "master":
        ns += to_master + to_module
    elif where == "neighbour":
        ns += sum(one_way(names[k], 2 + k - 1) for k in range(modules - 1, 0, -1))
    elif where != "local":
        raise ValueError(f"where: master, neighbour or local (got {where!r})")
    return ns / 1e3
