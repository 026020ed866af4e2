"""The running SnP cycle over the routed network of seed 002 (cell.snp.spacewire): two routers
with single redundancy between the master and the modules, each node's datagrams routed by path
address, every packet's return address routing its answer.

On the wire (UDP on loopback: one socket per router port, each joined to one node's socket, the
link):
- a node sends `path + packet`, the packet carrying the node's own return address (the path from a
  router back to it) in its SnP header; the router deletes the path byte it routes by
  (spacewire.Router: path addressing) and sends the rest out of that port;
- the receiving node takes the return address out of the header (its CRC made anew) and knows the
  sender by it: the master knows module k as its return address (2 + k,) whichever router it came
  through (both number their ports alike: spacewire.ring), and answers along it through the router
  it last heard that module on.

Before its cycle starts the master finds the network through each of its links
(`explore_routers`: spacewire.Explorer, RMAP reads of the routers' configuration ports): the port it
is on, and the paths to the nodes beyond, which it then explores for modules (NODE_INFO_QUERY, as
on a network of its own ports).  Nothing is declared to it but its two links.

So the master's and modules' sans-IO cores and their packet shapes stay as they are: the link
(`RoutedLink`) does the routing, as a SpaceWire node's network interface does.  A module that
hears nothing back for `failover_after` sends in a row moves to the other router (a permanent
failure of its path: spacewire.Redundant's rule, no retry).  `routers_main` runs both routers in a
process of their own.
"""

from __future__ import annotations

import contextlib
import select
import socket
import time
from dataclasses import dataclass
from typing import Any

from cell.sched import place
from cell.snp.link import (
    ROUTERS,
)
from cell.snp.native import RoutersState, _ip, available, library
from cell.snp.spacewire import End, Explorer, Packet, Router, RouterInfo


@dataclass(frozen=True)
class Explored:
    """What the master found through its links to the two routers."""

    links: tuple[Any, Any]  # its links' addresses, R1's then R2's
    routers: tuple[RouterInfo, RouterInfo]
    ends: tuple[tuple[int, ...], ...]  # the paths to the nodes beyond them, through either

    @property
    def own(self) -> tuple[int, ...]:
        """Its return address: the port it is on (the routers number their ports alike)."""
        return (self.routers[0].return_port,)


def explore_routers(sock: socket.socket, links: tuple[Any, Any], round_s: float = 0.05) -> Explored:
    """An Explorer through each link, its probes sent from sock; a round ends when each probe is
    answered or round_s has passed (a probe to a node is never answered: each round that reaches
    nodes takes round_s).  What else comes in meanwhile is dropped.  RuntimeError if no router
    answers on a link, or the two reach the master by different ports."""
    found = []
    for link in links:
        ex = Explorer()
        while not ex.done:
            for probe in ex.probes():
                sock.sendto(probe, link)
            end = time.monotonic() + round_s
            while ex.pending and (left := end - time.monotonic()) > 0:
                if select.select([sock], [], [], left)[0]:
                    with contextlib.suppress(BlockingIOError):
                        data, addr = sock.recvfrom(2048)
                        if addr == link:
                            ex.answer(data)
            ex.timeout()
        if () not in ex.routers:
            raise RuntimeError(f"no router answered the master's exploration on its link {link}")
        found.append(ex)
    r1, r2 = (ex.routers[()] for ex in found)
    if r1.return_port != r2.return_port:
        raise RuntimeError(f"the routers reach the master by ports {r1.return_port} and {r2.return_port}")
    ends = sorted({path for ex in found for path in ex.ends})
    return Explored(links, (r1, r2), tuple(ends))


@dataclass
class Routers:
    """The routers' process as its starter holds it (`start_routers`): the links of the master
    (R1's port, R2's) and of each module k, the orders a link cut and its end."""

    process: Any
    conn: Any
    master: tuple[Any, Any]
    modules: list[tuple[Any, Any]]

    def cut(self, router: int, port: int) -> None:
        """That link down, once the routers say it is."""
        self.conn.send(("cut", router, port))
        self.conn.recv()

    def ended(self) -> bool:
        """The process ended (it says nothing on its pipe until then)."""
        return self.conn.poll()

    def stop(self) -> dict:
        """End it: its counters (empty if it had ended already); killed if it does not end."""
        counts: dict = {}
        with contextlib.suppress(OSError, EOFError):
            self.conn.send(("stop", 0, 0))
            if self.conn.poll(10):
                counts = self.conn.recv()
        self.process.join(1.0)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(1.0)
        self.conn.close()
        return counts


def start_routers(
    ctx: Any,
    master_port: int,
    module_ports: list[int],
    until_s: float,
    rt_priority: int = 0,
    cpus: list[int] | None = None,
    native: bool | None = None,
) -> Routers:
    """routers_main in a process of ctx's, joined to the master's and the modules' ports on
    127.0.0.1 (module k's is its port 2 + k); native as routers_main's."""
    peers = [("127.0.0.1", master_port), *(("127.0.0.1", p) for p in module_ports)]
    here, there = ctx.Pipe()
    process = ctx.Process(
        target=routers_main, args=(there, peers, until_s, rt_priority, native, cpus), daemon=True
    )
    process.start()
    there.close()
    if not here.poll(30):
        raise RuntimeError("the routers' process did not start")
    r1, r2 = here.recv()
    return Routers(process, here, (r1[0], r2[0]), [(r1[1 + k], r2[1 + k]) for k in range(len(module_ports))])


def routers_main(
    conn: Any,
    peers: list[Any],
    until_s: float,
    rt_priority: int = 0,
    native: bool | None = None,
    cpus: list[int] | None = None,
) -> None:
    """Both routers until until_s (monotonic seconds) or the pipe says stop: port 1 of each joined
    to peers[0] (the master), port 2 + k to peers[1 + k] (module k).  Sends back each router's port
    addresses ([R1's, R2's], per port from 1), then takes ("cut", router, port) orders: that link
    down (what comes in or would go out on it is lost; the order sent back once done), or
    ("stop", ...): its counters go back.
    rt_priority: its SCHED_FIFO priority where allowed, over the nodes' (a router forwards as the
    packets come: under nodes that poll without sleeping at real-time priority, one at the normal
    policy would never run while they wait on it); cpus: where it runs (None: anywhere).  native:
    the routing in C (cell/snp/router.c; None: where it builds), else spacewire.Router in Python."""
    if rt_priority:
        place(cpus or [], rt_priority, -10)
    if native is None:
        native = available() is None
    routers = [Router(r + 1, len(peers)) for r in range(ROUTERS)]
    socks = {}
    for r in range(ROUTERS):
        for port in range(1, len(peers) + 1):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            s.setblocking(False)
            socks[r, port] = s
    conn.send([[socks[r, p].getsockname() for p in range(1, len(peers) + 1)] for r in range(ROUTERS)])
    counts: dict[str, Any] = {}
    try:
        run = _route_in_c if native else _route_in_python
        counts = run(conn, peers, socks, routers, until_s)
    finally:
        conn.send(counts)
        for s in socks.values():
            s.close()


def _order(conn: Any, routers: list[Router]) -> tuple[int, int] | None:
    """The caller's order: a link cut (router index, port: done on the Routers), or None to stop."""
    try:
        what, r, port = conn.recv()
    except EOFError:
        return None
    if what != "cut":
        return None
    routers[r].up.discard(port)
    conn.send(("cut", r, port))  # (done: what comes after meets it cut)
    return r, port


def _route_in_python(conn: Any, peers: list[Any], socks: dict, routers: list[Router], until_s: float) -> dict:
    where = {s.fileno(): key for key, s in socks.items()}
    ep = select.epoll()
    for s in socks.values():
        ep.register(s.fileno(), select.EPOLLIN)
    ep.register(conn.fileno(), select.EPOLLIN)
    dropped = 0
    try:
        while time.monotonic() < until_s:
            for fd, _ in ep.poll(0.05):
                if fd == conn.fileno():
                    if conn.poll() and _order(conn, routers) is None:
                        return _counts(dropped, routers)
                    continue
                r, port = where[fd]
                s, router = socks[r, port], routers[r]
                while True:
                    try:
                        data, addr = s.recvfrom(2048)
                    except BlockingIOError:
                        break
                    if port not in router.up or addr != peers[port - 1]:
                        dropped += 1  # (a link down, or a datagram from outside the link)
                        continue
                    for out_port, pkt in router.route(Packet(data, End.EOP)):
                        sends = router.configure(pkt.data, port) if out_port == 0 else [(out_port, pkt)]
                        for p, out in sends:  # (the configuration port answers by configure)
                            socks[r, p].sendto(out.data, peers[p - 1])
    finally:
        ep.close()
    return _counts(dropped, routers)


def _route_in_c(conn: Any, peers: list[Any], socks: dict, routers: list[Router], until_s: float) -> dict:
    import ctypes

    lib = library()
    st = RoutersState(n_ports=len(peers))
    for (r, port), s in socks.items():
        st.fd[r][port - 1], st.up[r][port - 1] = s.fileno(), 1
    for i, (host, port) in enumerate(peers):
        st.peer_ip[i], st.peer_port[i] = _ip(host), port
    until_ns = int(until_s * 1e9)
    while lib.snp_routers_run(ctypes.byref(st), until_ns, conn.fileno()) == 1:
        if (cut := _order(conn, routers)) is None:
            break
        st.up[cut[0]][cut[1] - 1] = 0
    for k, router in enumerate(routers):  # (C's counts, under spacewire.RouterCounters' names)
        c = router.counters
        c.forwarded, c.config = st.forwarded[k], st.config[k]
        for name, n in (
            ("bad_port", st.bad_port[k]),
            ("link_down", st.link_down[k]),
            ("no_route", st.no_route[k]),
            ("bad_config", st.bad_config[k]),
        ):
            c.dropped[name] = n
    return _counts(st.dropped, routers)


def _counts(dropped: int, routers: list[Router]) -> dict:
    return {"dropped": dropped, **{f"R{r.id}": r.counters.as_dict() for r in routers}}
