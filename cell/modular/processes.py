"""The modular robot on its real SnP cycle ([modular] transport = "cycle"): the master and the six
modules in processes of their own, as `cell bench snp` runs them, driven by the `modular` service.

- The master process serves a VdcMaster on its socket (its cycle path in C where it builds) and
  follows the references the service sends it (each motion's, from a start a little ahead);
- the modules process runs the six VdcModules on their own sockets, addresses and clocks (each off
  the host's by up to 2 ms and 50 ppm, servoed by SnP-TSP) and the MuJoCo Plant they drive; `unplug`
  pulls a module's socket out of the network as pulling its cable would, `plug` plugs a new one in
  (found by the master's exploration, configured, included: plug and operate);
- both report to the service over a pipe every REPORT_NS, in their management slot: the arm, the
  tool every ms, each module's clock offset, cycle time and misses, the master's view of each module.

CycleRobot is the service's side: ModularRobot's surface (cell.modular.robot.ArmRobot) over those
reports.  FDIR is the cycle's own (cell.snp.master.Master: guessed, suspect, lost); a lost module
stops the arm as in ModularRobot (the motion under way fails, the arm holds where it stood).
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import random
import shutil
import tempfile
import time
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from cell.modular.arm import ModularArm
from cell.modular.cycle import Plant, VdcMaster, tool_error_mm
from cell.modular.reference import CYCLE_NS, Reference
from cell.modular.robot import ArmRobot, Ended, ModuleState, Motion
from cell.ports import free_ports
from cell.sched import place
from cell.snp.link import module_port, open_udp
from cell.snp.modular import CycleConfig, NodeState
from cell.snp.native import available
from cell.snp.routed import Routers, explore_routers, start_routers
from cell.snp.runner import SPIN_NS, Slot, chain, run_modules, serve_master

REPORT_NS = 20_000_000  # each process's report to the service
LOST_NS_MIN = 50_000_000  # a module silent this long is lost, at the least (cell.snp.master.Master's)
LEAD_NS = 20_000_000  # a motion starts this long after the master takes it
MODULE0 = 101  # module ids: MODULE0 + joint, each plugged to the one before (the first to the base)
SLOT_NS, MANAGEMENT_NS = 30_000, 400_000  # at a 1 ms period (cell.bench.snp's schedule), in proportion
RT_PRIORITY = 50  # SCHED_FIFO of the two processes, where the OS allows: under the packet path's
# (robots 70, data plane 60), over what shares their core (under a busy core at the normal policy
# 97 % of the exchanges missed and the arm went on its brakes; at this priority 2 %, 0.45 mm)
PYTHON_PERIOD_NS = 4_000_000  # the cycle's period where it runs in Python (cell bench snp: VDC keeps
# up at 4 ms in Python, at 1 ms in C)


_STATE = {
    NodeState.INCLUDED: ModuleState.RUNNING,
    NodeState.SUSPECT: ModuleState.SUSPECT,
    NodeState.LOST: ModuleState.LOST,
}


def hold(q: np.ndarray) -> Reference:
    """A reference of one point: the arm holds q."""
    q = np.asarray(q, float)[None, :]
    z = np.zeros_like(q)
    return Reference("hold", np.zeros(1), q, z, z, np.zeros((1, 3)))


def save(ref: Reference, path: str) -> None:
    """A reference for the master: its q, qd, qdd as one (3, n, 6) array in a file (on tmpfs: handed
    over without a copy through a pipe, where a megabyte had kept the master from its cycle)."""
    np.save(path, np.stack([ref.q, ref.qd, ref.qdd]))


def load(path: str) -> Reference:
    """save's reference, mapped (the master's C path reads it where it lies)."""
    a = np.load(path, mmap_mode="r")
    n = a.shape[1]
    return Reference(os.path.basename(path), np.arange(n) * (CYCLE_NS / 1e9), a[0], a[1], a[2],
                     np.broadcast_to(np.zeros(3), (n, 3)))  # fmt: skip


def cycle_config(period: int) -> CycleConfig:
    """The cycle's schedule at `period` ns: cell.bench.snp's 1 ms one, stretched in proportion."""
    scale = period // CYCLE_NS
    return CycleConfig(
        period_ns=period, budget_ns=period, slot_ns=SLOT_NS * scale, management_ns=MANAGEMENT_NS * scale
    )


def _orders(conn: Any, parent: int) -> list[tuple] | None:
    """What the service asked since; None: stop (it asked, or it is gone: a process whose parent
    died ends with it)."""
    if os.getppid() != parent:
        return None
    out = []
    while conn.poll():
        msg = conn.recv()
        if msg[0] == "stop":
            return None
        out.append(msg)
    return out


# --- the master's process ---------------------------------------------------------------------------


def master_main(
    conn: Any,
    ports: list[int],
    native: bool,
    period: int,
    spin: bool,
    q0: list[float],
    suspect: int,
    lost_ns: int,
    net: tuple[int, Any] | None = None,
) -> None:
    """net: over the routers, (its own port, its two links): it explores the network through them
    and knows its modules by the paths to them, their return addresses (cell.snp.routed)."""
    place([], RT_PRIORITY, -5)
    config = cycle_config(period)
    sock = open_udp(port=net[0] if net else 0, timestamps=True)
    routes = explore_routers(sock, net[1]) if net else None
    where: list[Any] = list(routes.ends) if routes else [("127.0.0.1", p) for p in ports]
    master = VdcMaster(
        where, config, time.monotonic_ns, hold(np.array(q0)), suspect_cycles=suspect, lost_ns=lost_ns
    )
    master.vdc.start_ns = 0  # (holding from the start: no settling wait)
    parent, nxt = os.getppid(), 0

    following = 0  # the service's number of the reference followed (0: holding)

    def between() -> bool:
        nonlocal nxt, following
        now = time.monotonic_ns()
        if now < nxt:
            return False
        nxt = now + REPORT_NS
        orders = _orders(conn, parent)
        if orders is None:
            return True
        for what, *arg in orders:
            if what == "follow":  # (the reference's file, the service's number for it)
                master.vdc.follow(load(arg[0]), now + LEAD_NS)
                following = arg[1]
            elif what == "hold":  # where the master has the arm now
                master.vdc.follow(hold(np.array([master.vdc.guess(j, now) for j in range(6)])), now)
                following = 0
        states = [NodeState.FOUND] * 6  # (a joint no module has been configured for yet: joining)
        for n in master.nodes.values():
            if 0 <= n.joint < 6 and (n.state != NodeState.LOST or states[n.joint] == NodeState.FOUND):
                states[n.joint] = n.state
        conn.send((
            "master",
            {
                "states": [str(state) for state in states],
                "start_ns": master.vdc.start_ns,
                "following": following,
                "guessed": master.counters.guessed,
                "denied": master.handler.counters.denied.get("deadline_cannot_be_met", 0),
                "events": list(master.events)[-20:],
            },
        ))  # fmt: skip
        return False

    try:
        spin_ns = SPIN_NS if spin else 0
        serve_master(
            master, sock, between, spin_ns=spin_ns, native=native, stop_every_ns=REPORT_NS // 2, routes=routes
        )
    finally:
        sock.close()


# --- the modules' process ---------------------------------------------------------------------------


def modules_main(
    conn: Any,
    ports: list[int],
    native: bool,
    period: int,
    spin: bool,
    q0: list[float],
    where: tuple[str, ...],
    adapt: float,
    routes: list[Any] | None = None,
    seed: int = 1,
) -> None:
    place([], RT_PRIORITY, -5)
    config = cycle_config(period)
    plant = Plant(np.array(q0))
    spec = {
        s["module_id"]: s | {"port": p, "cd": cd, "adapt": adapt}  # (cd: "master", "local" or "neighbour")
        for s, p, cd in zip(chain(6, random.Random(seed), module0=MODULE0), ports, where, strict=True)
    }
    if routes is not None:  # (over the routers: module k's links and its port on them)
        for k, s in enumerate(spec.values()):
            s["routes"], s["route_port"] = routes[k], module_port(k)
    slots = [Slot(**s) for s in spec.values()]
    parent, t0, taken = os.getppid(), time.monotonic_ns(), 0
    cycles_taken: dict[int, int] = {}  # cycles taken so far, by id(slot)

    def control(now: int) -> bool:
        nonlocal taken
        orders = _orders(conn, parent)
        if orders is None:
            return True
        for what, *arg in orders:
            live = [s for s in slots if s.sock is not None and s.module_id == arg[0]]
            if what == "unplug" and live:
                live[0].unplug_s = (now - t0) / 1e9
            elif what == "plug" and not live and not any(s.module is None for s in slots):
                slots.append(Slot(**spec[arg[0]], plug_s=(now - t0) / 1e9))
        taken, records = plant.since(taken)
        modules = []
        for s in slots:
            m = s.module
            if s.sock is None or m is None:
                continue
            done = len(m.cycles)
            recent = m.cycles[cycles_taken.get(id(s), 0) :]
            cycles_taken[id(s)] = done
            modules.append({
                "module_id": s.module_id,
                "clock_offset_us": s.clock_errors[-1] / 1e3 if s.clock_errors else None,
                "missed": sum(m.missed.values()), "cycles": done, "cycle_ns": [c[2] - c[1] for c in recent],
            })  # fmt: skip
        d = plant.arm.data
        conn.send(("modules", {"q": d.qpos.tolist(), "records": records, "modules": modules}))
        return False

    run_modules(
        slots, float("inf"), native=native, plant=plant, control=control, sample_ns=REPORT_NS,
        sample_grid=config.management_grid, spin=spin,
    )  # fmt: skip


# --- the service's side -----------------------------------------------------------------------------


@dataclass
class _Running:
    """A motion the master follows: its reference (the approach and the path, one after the other),
    the generation the master gives it, its errors so far."""

    motion: Motion
    ref: Reference
    generation: int
    start_ns: int | None = None
    k: int = 0  # the reference's points the tool has been measured against


class CycleRobot(ArmRobot):
    """The modular robot on its SnP cycle (see the module docstring); call `cycle()` often (each ms
    in the service): it takes the processes' reports and ends motions."""

    def __init__(
        self,
        q0: np.ndarray,
        *,
        where: tuple[str, ...],
        adapt: float = 0.0,
        suspect_cycles: int = 3,
        lost_cycles: int = 20,
        native: bool | None = None,
        period_ns: int | None = None,
        spin: bool = True,
        routed: bool = False,
    ) -> None:
        """native: the cycle's hot paths in C (None: if they build here); period_ns: the cycle's
        (None: 1 ms in C, PYTHON_PERIOD_NS in Python); spin: the processes poll without sleeping
        through each cycle's exchanges (about half a core each at 1 ms; without, each datagram
        waits for a wake-up and more exchanges miss); routed: every datagram through the two
        routers of cell.snp.routed, in a third process."""
        super().__init__(where)
        self.transport = "cycle"
        self.native = available() is None if native is None else native
        self.period_ns = period_ns or (CYCLE_NS if self.native else PYTHON_PERIOD_NS)
        self.states = [ModuleState.JOINING] * 6
        self.stopped = "the modules are joining the cycle"
        self._q = np.asarray(q0, float).copy()
        self._arm = ModularArm(self._q)
        self.tool_ref = self.tool
        self._guessed = np.zeros(6, dtype=np.int64)
        self.unplugged: set[int] = set()
        self.master_report: dict[str, Any] = {}
        self._running: _Running | None = None
        self._generation = 0
        self._last_tool_t = 0
        self._files = tempfile.mkdtemp(
            prefix="cell-modular-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None
        )
        ctx = mp.get_context("spawn")
        self._conns = []
        self._procs = []
        ports = free_ports(6)
        # (the master's FDIR counts time; a module syncing its clock is silent for up to its
        # beacons' period between time packets: never under the master's own default)
        lost_ns = max(lost_cycles * self.period_ns, LOST_NS_MIN)
        self._routers: Routers | None = None
        net, links = None, None
        if routed:
            net, links = self._start_routers(ctx, ports)
        for target, args in (
            (master_main, (ports, self.native, self.period_ns, spin, list(q0), suspect_cycles, lost_ns, net)),
            (modules_main, (ports, self.native, self.period_ns, spin, list(q0), tuple(where), adapt, links)),
        ):
            here, there = ctx.Pipe()
            p = ctx.Process(target=target, args=(there, *args), daemon=True)
            p.start()
            there.close()
            self._conns.append(here)
            self._procs.append(p)

    def _start_routers(self, ctx: Any, ports: list[int]) -> tuple[tuple[int, Any], list[Any]]:
        """The routers' process (cell.snp.routed), over the cycle's two (as a switch: on their core,
        at a priority over theirs): (the master's port and links, each module's links)."""
        master_port = free_ports(1)[0]
        self._routers = net = start_routers(ctx, master_port, ports, time.monotonic() + 1e9, RT_PRIORITY + 5)
        return (master_port, net.master), net.modules

    # -- ArmRobot's ---------------------------------------------------------------------------------
    @property
    def q(self) -> np.ndarray:
        return self._q.copy()

    @property
    def tool(self) -> np.ndarray:
        return self._arm.tool_position(self._q)

    @property
    def guessed_by(self) -> np.ndarray:
        return self._guessed

    def frames(self) -> np.ndarray:
        d = self._arm.data
        d.qpos[:] = self._q
        mujoco.mj_kinematics(self._arm.model, d)
        return np.vstack([d.xanchor, d.site_xpos[self._arm.tool][None, :]])

    def counters(self) -> dict[str, float]:
        out = super().counters()
        for name, off in zip(self.NAMES, self.clock_offsets_us, strict=True):
            if np.isfinite(off):
                out[f"modular.{name}.clock_offset_us"] = float(off)
        out["modular.period_ms"] = self.period_ns / 1e6
        return out

    # -- what users ask ---------------------------------------------------------------------------
    def move(
        self, *, joints: list[float] | None = None, tool: list[float] | None = None, path: str = "",
        speed: float = 1.0,
    ) -> Motion:  # fmt: skip
        name, ref, then = self.plan(joints, tool, path, speed)
        whole = ref if then is None else _chain(ref, then)
        self.motion = m = Motion(name, whole, guessed_at_start=int(self._guessed.sum()))
        self._generation += 1
        self._running = _Running(m, whole, self._generation)
        file = os.path.join(self._files, f"reference-{self._generation}.npy")
        save(whole, file)
        self._send(0, "follow", file, self._generation)
        with contextlib.suppress(OSError):  # (the master has left the one before the last)
            os.unlink(os.path.join(self._files, f"reference-{self._generation - 2}.npy"))
        return m

    def unplug(self, name: str) -> None:
        i = self.module(name)
        self.unplugged.add(i)
        self.states[i] = ModuleState.UNPLUGGED
        self._send(1, "unplug", MODULE0 + i)

    def plug(self, name: str) -> None:
        i = self.module(name)
        if i in self.unplugged:
            self.unplugged.discard(i)
            self.states[i] = ModuleState.JOINING
            self._send(1, "plug", MODULE0 + i)

    # -- the reports ------------------------------------------------------------------------------
    def cycle(self) -> Ended | None:
        """Take what the processes reported; the motion that ended since, if one did."""
        for i, conn in enumerate(self._conns):
            try:
                while conn.poll():
                    what, report = conn.recv()
                    (self._master if what == "master" else self._modules)(report)
            except (EOFError, OSError):  # (its end of the pipe closed: the process ended)
                if not self.failed:
                    self.failed = self.stopped = f"the cycle's {('master', 'modules')[i]} process ended"
        if self._routers is not None and self._routers.ended() and not self.failed:
            self.failed = self.stopped = "the cycle's routers process ended"
        return self._progress()

    def _master(self, r: dict[str, Any]) -> None:
        """The master's view of each module: its state (an unplugged one stays so here), and a lost
        one stops the arm until every module runs again."""
        self.master_report = r
        seen = [NodeState(state) for state in r["states"]]
        for j, state in enumerate(seen):
            if j not in self.unplugged:
                self.states[j] = _STATE.get(state, ModuleState.JOINING)
        run = self._running
        if run is not None and r["following"] == run.generation:
            run.start_ns = r["start_ns"]
        gone = [
            f"{self.NAMES[j]} {self.states[j]}" for j, state in enumerate(seen) if state == NodeState.LOST
        ]
        if gone and not self.stopped:
            self.stopped = f"module {', '.join(gone)}: the arm holds where it stood until it is back"
            self._send(0, "hold")
        elif self.stopped and not self.failed and all(s is ModuleState.RUNNING for s in self.states):
            self.stopped = ""  # every module in the cycle: motions are taken (from where it holds)

    def _modules(self, r: dict[str, Any]) -> None:
        self._q = np.array(r["q"])
        for m in r["modules"]:
            j = m["module_id"] - MODULE0
            if m["clock_offset_us"] is not None:
                self.clock_offsets_us[j] = m["clock_offset_us"]
            self._guessed[j] = m["missed"]
            if m["cycle_ns"]:
                self.module_cycle_us[j] = float(np.mean(m["cycle_ns"])) / 1e3
                self.cycles = max(self.cycles, m["cycles"])
                self.cycle_ns_sum += int(np.sum(m["cycle_ns"])) // 6
                self.cycle_ns_max = max(self.cycle_ns_max, int(np.max(m["cycle_ns"])))
        run, records = self._running, r["records"]
        if not records:
            return
        self._last_tool_t = records[-1][0]
        if run is not None and run.start_ns is not None:  # (the tool every ms of the motion)
            errors = tool_error_mm(records, run.ref, run.start_ns)
            run.motion.errors_mm += errors.tolist()
            run.k += len(errors)
            k = (self._last_tool_t - run.start_ns) // CYCLE_NS
            if k >= 0:
                self.tool_ref = run.ref.tool[min(k, len(run.ref.t) - 1)]

    def _progress(self) -> Ended | None:
        run = self._running
        if run is None:
            return None
        m = run.motion
        if self.stopped and run.start_ns is not None:
            m.failed = self.stopped
        elif run.start_ns is None or self._last_tool_t < run.start_ns + len(run.ref.t) * CYCLE_NS:
            return None
        self._running = self.motion = None
        e = np.array(m.errors_mm or [0.0])
        return Ended(m.path, run.k, float(e.max()), float(np.sqrt(np.mean(e**2))),
                     int(self._guessed.sum()) - m.guessed_at_start, m.failed)  # fmt: skip

    def _send(self, i: int, *msg: Any) -> None:
        with contextlib.suppress(OSError, BrokenPipeError):
            self._conns[i].send(msg)

    def close(self) -> None:
        """Stop both processes (killed if they do not end within a second)."""
        for i in range(2):
            self._send(i, "stop")
        for p in self._procs:
            p.join(1.0)
            if p.is_alive():
                p.kill()
                p.join(1.0)
        for c in self._conns:
            c.close()
        if self._routers is not None:
            self._routers.stop()
        shutil.rmtree(self._files, ignore_errors=True)


def _chain(a: Reference, b: Reference) -> Reference:
    """a, then b (b's first point is a's last: the approach ends where the path starts)."""
    t = np.concatenate([a.t, a.t[-1] + CYCLE_NS / 1e9 + b.t])
    return Reference(
        b.name,
        t,
        *(np.concatenate([x, y]) for x, y in ((a.q, b.q), (a.qd, b.qd), (a.qdd, b.qdd), (a.tool, b.tool))),
    )
