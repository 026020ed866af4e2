"""The data-plane bench's targets: each a child process that serves the generator's statuses (the
data plane in numpy, C or XDP, loaded or taking updates; a bare reflector; a naive controller; one
driver process per robot) and puts the address it serves on into `out`."""

from __future__ import annotations

import asyncio
import socket
import subprocess
import sys
from collections.abc import Callable
from typing import Any

import numpy as np

from cell import aio
from cell.bench import pin
from cell.bench.driver import NaiveDriver
from cell.bench.xdpnet import XDP_PORT, xdp_dataplane
from cell.ports import free_port
from cell.robot import udp

PRELOAD = 40_000  # TPs loaded before an updating run, for its deletes


def _updating_target(robots: int, out: Any, stop: Any) -> None:
    _dataplane_target(robots, out, stop, updates=True)


def _dataplane_target(robots: int, out: Any, stop: Any, updates: bool = False, net: Any = None) -> None:
    """The data plane service's packet path: numpy here, or (net: the switch's XdpConfig) the XDP
    program attached in the switch's namespace, this process its control plane."""
    pin(1)
    from cell.dataplane.tables import Refused

    try:
        plane = _loaded_plane(robots, net, updates)
    except Exception as exc:  # (past the target's capacity: the search's limit, told to the parent)
        out.put({"error": str(exc) if isinstance(exc, Refused) else f"{type(exc).__name__}: {exc}"})
        return
    out.put(plane.sock.getsockname())
    _serve(plane, robots, out, stop, updates)


def _loaded_plane(robots: int, net: Any, updates: bool) -> Any:
    """A data plane with `robots` robots, each heading for its own TP (and the TPs updates delete)."""
    from cell.config import load_config
    from cell.dataplane.plane import DataPlane, XdpDataPlane
    from cell.dataplane.tables import TP

    rob = [{"id": r, "name": f"b{r}", "skill_port": 20000 + r} for r in range(1, robots + 1)]
    if net is None:
        listen = f"127.0.0.1:{free_port(socket.SOCK_DGRAM)}"
        cfg = load_config(overrides={"robots": rob, "dataplane": {"listen": listen}})
        plane = DataPlane(cfg)
    else:
        plane = XdpDataPlane(load_config(overrides={"robots": rob, "dataplane": xdp_dataplane(net)}))
    # every robot heads for a TP 0.1 rad away, forever (a self-loop): the full egress path for each packet
    plane.tables.insert([TP(r, 1, 1, 1.0, [0.1] * 6, [0.0] * 6) for r in range(1, robots + 1)])
    for r in range(1, robots + 1):
        plane.tables.set_registers(r, 1, 2**62)
    if updates:  # the old TPs the updates will delete, loaded before the load starts
        old_tps = [TP(1 + i % robots, 1000 + i, 1000 + i, 1.0, [0.0] * 6, [0.0] * 6) for i in range(PRELOAD)]
        plane.tables.insert(old_tps)
    return plane


def _serve(plane: Any, robots: int, out: Any, stop: Any, updates: bool) -> None:
    """Run the loaded data plane until `stop`, a controller's updates each second with `updates`."""
    from cell.dataplane.tables import TPBatch
    from cell.dataplane.wire import encode_keys, encode_tps

    update_ms: list[float] = []
    hold_ms: list[float] = []  # the longest the packet path waited, per update

    async def updater() -> None:
        """Each second, as a controller would: insert 1,600 new TPs and delete 10,000 old ones."""
        from cell.v1 import dataplane_pb2

        fresh, old = 100_000, 1000
        while True:
            await asyncio.sleep(1.0)
            req = dataplane_pb2.TableUpdate()
            ids = np.arange(fresh, fresh + 1_600)
            zeros, n = np.zeros(ids.size * 6), ids.size
            new = TPBatch.from_flat(1 + ids % robots, ids, ids, np.ones(n), np.full(n, 6), zeros, zeros)
            encode_tps(new, req.insert)
            gone = np.arange(old, min(old + 10_000, 1000 + PRELOAD))
            encode_keys(np.stack([1 + (gone - 1000) % robots, gone], axis=1), req.remove)
            req = dataplane_pb2.TableUpdate.FromString(req.SerializeToString())  # as it arrives from the bus
            reply = await plane.update(req)
            update_ms.append(reply.total_ms)
            hold_ms.append(reply.apply_us / 1e3)
            fresh, old = fresh + 1_600, old + 10_000

    async def main() -> None:
        tasks = [asyncio.ensure_future(plane.run())]
        if updates:
            tasks.append(asyncio.ensure_future(updater()))
        await asyncio.to_thread(stop.wait)
        for t in tasks:
            t.cancel()

    aio.run(main())
    out.put(
        {"batches": plane.batches, "packets": plane.packets_in, "update_ms": update_ms, "hold_ms": hold_ms}
    )
    plane.close()


def _xdp_target(robots: int, out: Any, stop: Any, net: Any) -> None:
    _dataplane_target(robots, out, stop, net=net)


def _xdp_updating_target(robots: int, out: Any, stop: Any, net: Any) -> None:
    _dataplane_target(robots, out, stop, updates=True, net=net)


def _xdp_reflector_target(robots: int, out: Any, stop: Any, net: Any) -> None:
    """The bare XDP reflector in the switch's namespace: every datagram straight back (XDP_TX)."""
    from cell.dataplane.xdp.program import XdpProgram
    from cell.dataplane.xdp.switch import in_namespace

    program = XdpProgram(1, 2, 1)
    try:
        program.globals["listen_port"] = socket.htons(XDP_PORT)
        in_namespace(net.netns, lambda: program.attach(socket.if_nametoindex(f"{net.veth}1"), reflect=True))
        out.put((net.switch_addr, XDP_PORT))
        stop.wait()
    finally:
        in_namespace(net.netns, program.detach)
        program.close()


def _reflector_target(robots: int, out: Any, stop: Any) -> None:
    from cell.bench.robots import reflector

    reflector(out, stop, True, 1)


def _naive_target(robots: int, out: Any, stop: Any) -> None:
    pin(1)

    async def main() -> None:
        loop = asyncio.get_running_loop()
        proto = NaiveDriver({r: [0.1] * 6 for r in range(1, robots + 1)})
        sock = udp.open_socket("127.0.0.1", gro=False)
        transport, _ = await loop.create_datagram_endpoint(lambda: proto, sock=sock)
        out.put(sock.getsockname())
        await asyncio.to_thread(stop.wait)
        transport.close()
        out.put({"answered": proto.answered})

    aio.run(main())


def _drivers_target(robots: int, out: Any, stop: Any) -> None:
    """App. B's baseline: one driver process per arm (cell.bench.driver), all on core 1 as the data
    plane is; their addresses and pids told to the load."""
    pin(1)
    cmd = [sys.executable, "-m", "cell.bench.driver"]
    procs = [
        subprocess.Popen([*cmd, str(r)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        for r in range(1, robots + 1)
    ]
    try:
        ports = []
        for p in procs:
            assert p.stdout is not None  # (stdout=PIPE)
            ports.append(int(p.stdout.readline()))
        out.put({"addrs": [("127.0.0.1", port) for port in ports], "pids": [p.pid for p in procs]})
        stop.wait()
    finally:
        for p in procs:
            assert p.stdin is not None  # (stdin=PIPE)
            p.stdin.close()  # (each driver ends when its stdin does)
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()


TARGETS: dict[str, Callable[..., None]] = {
    "xdp": _xdp_target,
    "xdp+updates": _xdp_updating_target,
    "xdp-reflector": _xdp_reflector_target,
    "dataplane": _dataplane_target,
    "dataplane+updates": _updating_target,
    "reflector": _reflector_target,
    "naive": _naive_target,
    "drivers": _drivers_target,
}
