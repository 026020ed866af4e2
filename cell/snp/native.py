"""The joint modules' cycle in C (cell/snp/cycle.c), built on first use and driven from Python.

`NativeCycles` runs the [A, B] and [C, D] exchanges of every running module of a process
(transport "snp") in one C loop on their own sockets, and hands back every other datagram:
the Python `JointModule` still does configuration, SnP-TSP and node info, and its clock servo
is what the C loop reads the master's time through.  The library is compiled with the system's
C compiler (`cc`, or $CC) into a cache keyed by the source's hash; `available()` says whether
that worked and, if not, why (the Python modules then run the cycle themselves).
"""

from __future__ import annotations

import ctypes
import functools
import os
import socket
from pathlib import Path
from typing import Any, Protocol, cast

import numpy as np

from cell.native import NativeUnavailable, build
from cell.snp.link import RoutedLink
from cell.snp.master import Master, Node
from cell.snp.modular import _IDS, NodeState, Stage
from cell.snp.modular import ModuleState as ModuleLife  # (ModuleState here: the C mirror)
from cell.snp.module import JointModule

HERE = Path(__file__).parent
SOURCES = (HERE / "cycle.c", HERE / "master.c", HERE / "router.c")  # one library; all include wire.h
HEADERS = (HERE / "wire.h",)
RECORDS = 256
RUN_UNTIL, RUN_HANDED, RUN_RECORDS_FULL, RUN_EVENT = 0, 1, 2, 3
_I, _D = ctypes.c_int64, ctypes.c_double


class _VdcModule(Protocol):
    """A module whose cycle runs more in C (cell.modular.cycle.VdcModule: it has to_c)."""

    def from_c(self, v: VdcModuleState) -> None: ...


class _VdcModel(Protocol):
    """A master's model that runs more in C (cell.modular.cycle.VdcModel: it has to_c)."""

    generation: int

    def reference_to_c(self, v: VdcState) -> list[np.ndarray]: ...

    def from_c(self, v: VdcState) -> None: ...


class PlantState(ctypes.Structure):
    """plant_t of cycle.c: a cell.modular.cycle.Plant stepped in C."""

    _fields_ = [
        *((name, _I) for name in ("dof", "dt_ns", "period_ns", "cap")),
        *((name, ctypes.c_void_p) for name in ("model", "data", "step", "qpos", "qvel", "ctrl", "tool")),
        *(
            (name, ctypes.c_void_p)
            for name in ("clock", "tau", "hold", "limit", "driven", "rec_t", "rec_tool")
        ),
        ("kp", _D),
        ("kd", _D),
    ]


class RouteState(ctypes.Structure):
    """route_t of wire.h: a node's link over the two routers in C (cell.snp.link.RoutedLink)."""

    _fields_ = [
        ("on", _I),
        ("own", _I),
        ("ip", _I * 2),
        ("port", _I * 2),
        *((name, _I) for name in ("active", "unheard", "failover_after", "failovers", "refused")),
        ("via", _I * 256),
    ]
    on: int
    own: int
    active: int
    unheard: int
    failover_after: int
    failovers: int
    refused: int

    def take(self, link: Any) -> None:
        """The Python link's state into C (a RoutedLink: on; else off): before each C run, as
        `give` after it, so that each side goes on from what the other did."""
        if not isinstance(link, RoutedLink):
            self.on = 0
            return
        self.on, self.own = 1, link.own[0]
        for i, (host, port) in enumerate(link.links):
            self.ip[i], self.port[i] = _ip(host), port
        self.active, self.unheard, self.failover_after = link.active, link.unheard, link.failover_after or 0
        if not self.failover_after:  # (the master's: where it last heard each module)
            for ret, addr in link.via.items():
                self.via[ret[0]] = link.links.index(addr)

    def give(self, link: Any) -> None:
        """C's state of the link back into the Python link (its counters added)."""
        if not self.on:
            return
        link.active, link.unheard = self.active, self.unheard
        link.failovers, link.refused = link.failovers + self.failovers, link.refused + self.refused
        self.failovers = self.refused = 0
        if not self.failover_after:  # (R1, index 0: where an address not heard yet goes, on either side)
            link.via.update({(k,): link.links[v] for k, v in enumerate(self.via) if v or (k,) in link.via})


ROUTER_PORTS, ROUTERS = 31, 2


class RoutersState(ctypes.Structure):
    """routers_t of router.c: the two routers of cell.snp.routed in C."""

    _fields_ = [
        ("n_ports", _I),
        ("fd", (_I * ROUTER_PORTS) * ROUTERS),
        ("peer_ip", _I * ROUTER_PORTS),
        ("peer_port", _I * ROUTER_PORTS),
        ("up", (_I * ROUTER_PORTS) * ROUTERS),
        *(
            (name, _I * ROUTERS)
            for name in ("forwarded", "config", "bad_port", "link_down", "no_route", "bad_config")
        ),
        ("dropped", _I),
    ]


class VdcModuleState(ctypes.Structure):
    """vdc_module_t of cycle.c: a cell.modular.cycle.VdcModule's cycle in C."""

    _fields_ = [
        ("joint", _I),
        ("b_ids", _I * 20),
        ("f_ids", _I * 6),
        ("inertia", _D * 36),
        ("k", _D * 6),
        *((name, _D) for name in ("joint_gain", "armature", "damping", "torque_max")),
        ("b", _D * 20),
        ("tau_r", _D),
        ("qd", _D),
        ("have_b", _I),
        ("fresh", _I),
        *((name, _I) for name in ("safe_after", "missed_run", "braked")),
        ("local", _I),
        ("g_ids", _I * 6),
        ("g", _D * 6),
        ("f_star", _D * 6),
        ("adapt", _D),
        ("theta", _D * 10),
        ("bound", _D * 10),
        ("mass0", _D),
        *((name, _I) for name in ("neighbour", "tip", "nb_ip", "nb_port")),
        ("g_in_ids", _I * 6),
        ("body_pos", _D * 3),
        ("body_rot", _D * 9),
        ("q", _D),
        ("g_early_at", _I),
        ("g_early", _D * 6),
        ("plant", ctypes.POINTER(PlantState)),
    ]


class ModuleState(ctypes.Structure):
    """module_t of cycle.c, field for field."""

    _fields_ = [
        *((name, _I) for name in ("fd", "active", "source_process", "master_ip", "master_port")),
        ("ids", _I * 5),
        *((name, _I) for name in ("period_ns", "phase_ns", "budget_ns", "osc_origin", "osc_offset")),
        ("osc_drift", _D),
        ("servo_anchor", _I),
        ("servo_base", _I),
        ("servo_rate", _D),
        ("loss", _D),
        ("vdc", ctypes.POINTER(VdcModuleState)),
        *((name, _D) for name in ("pos", "vel", "v_des", "torque")),
        *((name, _I) for name in ("next_start", "scheduled", "start", "deadline", "qid", "stage")),
        *((name, _I) for name in ("missed_now", "missed_ab", "missed_cd", "overruns", "sent", "lost")),
        *((name, _I) for name in ("errors", "late", "n_records")),
        ("records", (_I * 4) * RECORDS),
        ("route", RouteState),
    ]


class JointEntry(ctypes.Structure):
    """joint_t of master.c: a joint's module and its part of the arm model."""

    _fields_ = [
        *((name, _I) for name in ("state", "ip", "port", "phase_ns")),
        ("ids", _I * 5),
        *((name, _D) for name in ("pos", "vel", "force")),
        *((name, _I) for name in ("at", "a_cycle", "heard_ns", "silent_cycles", "checked")),
    ]


MAX_JOINTS, QUEUE, EVENTS = 16, 64, 32
NODE_OFF, NODE_INCLUDED, NODE_SUSPECT, NODE_LOST = 0, 1, 2, 3
_NODE_STATE = {NodeState.INCLUDED: NODE_INCLUDED, NodeState.SUSPECT: NODE_SUSPECT}
_EVENT = {1: "silent", 2: "back", 3: "lost"}


VDC_JOINTS = 6


class VdcState(ctypes.Structure):
    """vdc_t of master.c: VDC's master (cell.modular.cycle.VdcModel) in C."""

    _fields_ = [
        *((name, _I) for name in ("n_ref", "ref_dt_ns", "start_ns", "settle_ns")),
        ("lam", _D),
        *((name, ctypes.c_void_p) for name in ("q_ref", "qd_ref", "qdd_ref")),
        ("b_ids", (_I * 20) * VDC_JOINTS),
        ("f_ids", (_I * 6) * VDC_JOINTS),
        ("body_pos", (_D * 3) * VDC_JOINTS),
        ("body_rot", (_D * 9) * VDC_JOINTS),
        ("f_star", (_D * 6) * VDC_JOINTS),
        ("seq", _I * VDC_JOINTS),
        ("key_cycle", _I * VDC_JOINTS),
        ("key_seq", (_I * VDC_JOINTS) * VDC_JOINTS),
        ("b", (_D * 20) * VDC_JOINTS),
        ("rot", (_D * 9) * VDC_JOINTS),
        ("carry", (_D * 18) * VDC_JOINTS),
        ("g_ids", (_I * 6) * VDC_JOINTS),
    ]


class MasterState(ctypes.Structure):
    """master_t of master.c, field for field."""

    _fields_ = [
        *((name, _I) for name in ("fd", "period_ns", "phase_ns", "budget_ns", "t0", "suspect_cycles")),
        *((name, _I) for name in ("lost_ns", "floor_ns")),
        *((name, _D) for name in ("gain", "margin", "loss")),
        ("service_ns", _I),
        ("vdc", ctypes.POINTER(VdcState)),
        ("joints", JointEntry * MAX_JOINTS),
        *((name, _I) for name in ("queries", "replies", "denied", "late", "guessed", "sent", "lost")),
        *((name, _I) for name in ("errors", "n_events")),
        ("events", (_I * 3) * EVENTS),
        ("n_pending", _I),
        ("seq", _I),
        ("pending", (_I * 13) * QUEUE),
        ("route", RouteState),
    ]


class Handed(ctypes.Structure):
    _fields_ = [(name, _I) for name in ("index", "len", "at", "ip", "port")]


def _ip(host: str) -> int:
    """An IPv4 address as the C side holds it (host order)."""
    return int.from_bytes(socket.inet_aton(host), "big")


def c_addr(addr: Any) -> tuple[int, int]:
    """A node's address as the C side holds it: (ip, port), or over routers (0, its return address)."""
    return (0, addr[0]) if len(addr) == 1 else (_ip(addr[0]), addr[1])


def _sender(h: Handed) -> tuple[str, int]:
    """The (host, port) of a datagram the C side handed back."""
    return socket.inet_ntoa(h.ip.to_bytes(4, "big")), h.port


@functools.cache
def library() -> ctypes.CDLL:
    """The built library (built now if its cached copy is missing); NativeUnavailable if it cannot be."""
    lib = build("snp-cycle", SOURCES, HEADERS)
    lib.snp_cycle_init.argtypes, lib.snp_cycle_init.restype = [ctypes.c_uint64], ctypes.c_int
    lib.snp_cycle_run.restype = ctypes.c_int
    lib.snp_cycle_run.argtypes = [
        ctypes.POINTER(ctypes.POINTER(ModuleState)), ctypes.c_int, _I, _I, _I, _I,
        ctypes.c_char_p, _I, ctypes.POINTER(Handed),
    ]  # fmt: skip
    lib.snp_plant_advance.argtypes, lib.snp_plant_advance.restype = [ctypes.POINTER(PlantState), _I], None
    lib.snp_master_init.argtypes, lib.snp_master_init.restype = [ctypes.c_uint64], ctypes.c_int
    lib.snp_master_run.restype = ctypes.c_int
    lib.snp_master_run.argtypes = [
        ctypes.POINTER(MasterState), _I, _I, _I, _I, ctypes.c_char_p, _I, ctypes.POINTER(Handed),
    ]  # fmt: skip
    lib.snp_routers_run.argtypes, lib.snp_routers_run.restype = (
        [ctypes.POINTER(RoutersState), _I, _I],
        ctypes.c_int,
    )
    lib.snp_routers_size.argtypes, lib.snp_routers_size.restype = [], ctypes.c_int
    for init, mirror in (
        (lib.snp_cycle_init, ModuleState),
        (lib.snp_master_init, MasterState),
        (lambda _: lib.snp_routers_size(), RoutersState),
    ):
        size = init(0)
        if size != ctypes.sizeof(mirror):
            raise NativeUnavailable(f"{mirror.__name__} is {ctypes.sizeof(mirror)} bytes, {size} in C")
    return lib


def available() -> str | None:
    """None if the C cycle can run here, else why not."""
    try:
        library()
    except (NativeUnavailable, OSError) as e:
        return str(e)
    return None


class NativeCycles:
    """The C loop for a process's modules: `attach` a module (its socket and oscillator), `run`
    until a time, take what it handed back.  A module's cycle moves to C once its Python
    `JointModule` is running with transport "snp"; its records, misses and link counters come
    back into the JointModule (and the caller's counters) after each run."""

    def __init__(self, *, spin_ns: int, lead_ns: int, mono_of_real: int, seed: int = 1) -> None:
        self.lib = library()
        self.lib.snp_cycle_init(seed)
        self.spin_ns, self.lead_ns, self.mono_of_real = spin_ns, lead_ns, mono_of_real
        self.buf = ctypes.create_string_buffer(2048)
        self.handed = Handed()
        self._states: dict[int, ModuleState] = {}  # by fd
        self._run_key: tuple[int, ...] = ()
        self._run_arr: Any = None
        self.plant: PlantState | None = None  # the modular arm the modules drive (VdcModule's)
        self._vdc: dict[int, VdcModuleState] = {}  # by fd

    def drive(self, plant: Any) -> None:
        """Step a cell.modular.cycle.Plant in C, through its arrays and MuJoCo's own mj_step (its
        model and data by the Python bindings' `_address`: the C structs they wrap)."""
        import mujoco

        lib = ctypes.CDLL(next(Path(mujoco.__file__).parent.glob("libmujoco.so*")).as_posix())
        arm = plant.arm
        d = arm.data
        self._plant_ref = plant  # (its arrays must outlive the runs)
        self.plant = PlantState(
            dof=arm.dof, dt_ns=plant.dt_ns, period_ns=plant.period_ns, cap=len(plant.rec_t),
            model=arm.model._address, data=d._address, step=ctypes.cast(lib.mj_step, ctypes.c_void_p).value,
            qpos=d.qpos.ctypes.data, qvel=d.qvel.ctypes.data, ctrl=d.ctrl.ctypes.data,
            tool=d.site_xpos.ctypes.data + 24 * arm.tool, clock=plant.time.ctypes.data,
            tau=plant.tau.ctypes.data, hold=plant.hold.ctypes.data, limit=plant.limit.ctypes.data,
            driven=plant.driven.ctypes.data, rec_t=plant.rec_t.ctypes.data,
            rec_tool=plant.rec_tool.ctypes.data, kp=plant.brake[0], kd=plant.brake[1],
        )  # fmt: skip

    def attach(self, fd: int, osc: Any, loss: float = 0.0) -> ModuleState:
        st = ModuleState(fd=fd, osc_origin=osc.origin, osc_offset=osc.offset_ns, osc_drift=osc.drift)
        st.loss = loss
        self._states[fd] = st
        self._run_key = ()
        return st

    def state(self, fd: int) -> ModuleState:
        return self._states[fd]

    def detach(self, fd: int) -> None:
        self._states.pop(fd, None)
        self._vdc.pop(fd, None)
        self._run_key = ()  # (a new socket may get its number)

    def push(self, st: ModuleState, m: JointModule, master: Any, inboard: Any = None) -> None:
        """What the Python module decided since the last run: its servo, its configuration and,
        once it runs with transport snp, the cycle handed to C (where it then stays).  inboard: the
        address of the module it is plugged to (a "neighbour" [C, D] passes its force there); over
        routers, addresses are return addresses (cell.snp.routed)."""
        s = m.servo
        st.servo_anchor, st.servo_base, st.servo_rate = s.anchor_raw, s.base, s.rate
        if st.active or m.state != ModuleLife.RUNNING or m.transport != "snp" or master is None:
            return
        c = m.config
        assert c is not None
        st.master_ip, st.master_port = c_addr(master)
        st.source_process = m.source_process
        st.ids[:] = _IDS[m.joint]
        st.period_ns, st.phase_ns, st.budget_ns = c.period_ns, c.phase_ns, c.budget_ns
        st.pos, st.vel, st.v_des, st.torque = m.pos, m.vel, m.v_des, m.torque
        st.next_start, st.qid, st.stage = m.next_start, m._qid, 0
        to_c = getattr(m, "to_c", None)  # (a module that runs more in C: the modular arm's VDC)
        if to_c is not None:
            if self.plant is None:
                raise ValueError("a VDC module's cycle in C needs its plant (drive(plant) first)")
            self._vdc[st.fd] = v = to_c(self.plant, inboard)
            st.vdc = ctypes.pointer(v)
        st.active = 1

    def pull(self, st: ModuleState, m: JointModule, link: Any) -> None:
        """The C loop's records and counters into the module and its link (then zeroed in C)."""
        if not st.active:
            return
        v = self._vdc.get(st.fd)
        if v is not None:  # (its VDC's state as C has it: its cycle goes on in Python from there)
            cast(_VdcModule, m).from_c(v)  # (the module that gave to_c)
        n = st.n_records
        if n:  # (one copy of the block: element by element, 256 records of six modules took 4 ms)
            recs = np.frombuffer(st.records, np.int64, 4 * n).reshape(n, 4)
            m.cycles.extend((a, b, c, d) for a, b, c, d in recs.tolist())
        m.missed[Stage.AB] += st.missed_ab
        m.missed[Stage.CD] += st.missed_cd
        m.overruns += st.overruns
        m.late += st.late
        m.pos, m.vel, m.v_des, m.torque, m._qid = st.pos, st.vel, st.v_des, st.torque, st.qid
        link.sent, link.lost, link.errors = link.sent + st.sent, link.lost + st.lost, link.errors + st.errors
        for name in ("n_records", "missed_ab", "missed_cd", "overruns", "sent", "lost", "errors", "late"):
            setattr(st, name, 0)

    def run(self, fds: list[int], until: int) -> tuple[int, int, bytes, int, tuple[str, int]] | None:
        """Run the cycles of the modules on these sockets until host time `until`; None then, or
        (code RUN_RECORDS_FULL, ...) when records must be taken, or (RUN_HANDED, the socket's fd,
        the datagram, its arrival (CLOCK_MONOTONIC ns), its sender)."""
        key = tuple(fds)
        if key != self._run_key:  # (the arguments built once for a set of modules: 15 us for six)
            states = [self._states[fd] for fd in fds]
            self._run_key = key
            self._run_arr = (ctypes.POINTER(ModuleState) * len(states))(*(ctypes.pointer(s) for s in states))
        h = self.handed
        code = self.lib.snp_cycle_run(
            self._run_arr, len(key), until, self.mono_of_real, self.spin_ns, self.lead_ns, self.buf, 2048, h
        )
        if code < 0:
            raise OSError(-code, os.strerror(-code))
        if code == RUN_UNTIL:
            return None
        if code == RUN_RECORDS_FULL:
            return code, -1, b"", 0, ("", 0)
        return code, fds[h.index], self.buf.raw[: h.len], h.at, _sender(h)


class NativeMaster:
    """The C path of a Python `Master` on its socket: `run` serves the included modules' A and C
    (admitted, answered earliest deadline first, or denied) and keeps FDIR's per-cycle watch
    until a time, an FDIR event or a datagram it hands back.  While a joint's cycle runs in C, C
    holds its part of the arm model and its FDIR state; `push` and `pull` carry them over to the
    Python master before and after each run, so between runs the Python master is whole (its
    generic queries, RMAP, beacons and exploration see the same model)."""

    def __init__(self, master: Master, fd: int, *, spin_ns: int, lead_ns: int, mono_of_real: int) -> None:
        self.lib = library()
        self.lib.snp_master_init(1)
        if master.model.joints > MAX_JOINTS:
            raise ValueError(f"the C master takes at most {MAX_JOINTS} joints")
        c, h = master.config, master.handler
        self.master, self.spin_ns, self.lead_ns, self.mono_of_real = master, spin_ns, lead_ns, mono_of_real
        self.st = MasterState(
            fd=fd, period_ns=c.period_ns, phase_ns=c.phase_ns, budget_ns=c.budget_ns, t0=master.model.t0,
            suspect_cycles=master.suspect_cycles, lost_ns=master.lost_ns, floor_ns=h.floor_ns,
            gain=c.gain, margin=h.margin, service_ns=h.floor_ns,
        )  # fmt: skip
        self.buf = ctypes.create_string_buffer(2048)
        self.handed = Handed()
        self._node: list[Node | None] = [None] * MAX_JOINTS  # the node each joint entry holds
        # a model that runs more in C (the modular arm's VDC: its to_c) gives its state, and the
        # reference it follows, whose arrays C reads where numpy holds them (kept alive here)
        to_c = getattr(master.model, "to_c", None)
        self.vdc: VdcState | None = to_c() if to_c is not None else None
        if self.vdc is not None:
            self._reference(self.vdc)
            self.st.vdc = ctypes.pointer(self.vdc)

    def _reference(self, vdc: VdcState) -> None:
        model = cast(_VdcModel, self.master.model)  # (the model that gave to_c)
        self._ref = model.reference_to_c(vdc)
        self._generation = model.generation

    def push(self) -> None:
        """The Python master's view into C: which modules are included (a newly included one with
        its address, items, slot and model entries), what Python heard from them, and the
        reference a VDC master was given to follow since."""
        ms, model, st = self.master, self.master.model, self.st
        if self.vdc is not None and cast(_VdcModel, model).generation != self._generation:
            self._reference(self.vdc)
        held: list[Node | None] = [None] * MAX_JOINTS
        for node in ms.nodes.values():
            if node.state in _NODE_STATE and 0 <= node.joint < MAX_JOINTS:
                held[node.joint] = node
        for j, n in enumerate(held):
            e = st.joints[j]
            if n is None:
                e.state = NODE_OFF
                continue
            if self._node[j] is not n or e.state not in (NODE_INCLUDED, NODE_SUSPECT):  # new to C
                (e.ip, e.port), e.phase_ns, e.ids[:] = c_addr(n.addr), n.phase_ns, _IDS[j]
                e.pos, e.vel, e.force, e.at = model.pos[j], model.vel[j], model.force[j], model.at[j]
            e.state, e.heard_ns, e.silent_cycles = _NODE_STATE[n.state], n.heard_ns, n.silent_cycles
            e.checked, e.a_cycle = n.checked, ms._a_cycle.get(j, -1)
        self._node = held

    def pull(self, link: Any) -> None:
        """What C did into the Python master: its model entries and FDIR state, its counters
        (the master's, its handler's and the link's), its events (a lost module excluded)."""
        ms, model, st = self.master, self.master.model, self.st
        if self.vdc is not None:
            cast(_VdcModel, model).from_c(self.vdc)  # (the model that gave to_c)
        for j, n in enumerate(self._node):
            if n is None:
                continue
            e = st.joints[j]
            model.pos[j], model.vel[j], model.force[j], model.at[j] = e.pos, e.vel, e.force, e.at
            n.heard_ns, n.silent_cycles, n.checked = e.heard_ns, e.silent_cycles, e.checked
            if e.a_cycle >= 0:
                ms._a_cycle[j] = e.a_cycle
            if e.state in (NODE_INCLUDED, NODE_SUSPECT):
                n.state = NodeState.INCLUDED if e.state == NODE_INCLUDED else NodeState.SUSPECT
        for i in range(st.n_events):  # (in the order they happened)
            t, what, j = st.events[i]
            n = self._node[j]
            if n is None or n.state == NodeState.LOST:
                continue
            if _EVENT[what] == "lost":
                ms.lose(n, t)
            else:
                ms.events.append((t, _EVENT[what], n.info.module_id, j))
        for j, n in enumerate(self._node):  # (a loss whose event did not fit in the ring)
            if n is not None and st.joints[j].state == NODE_LOST and n.state != NodeState.LOST:
                ms.lose(n, n.heard_ns + ms.lost_ns)
        h = ms.handler.counters
        h.queries += st.queries
        h.replies += st.replies
        h.count("denied", "deadline_cannot_be_met", st.denied)
        h.late += st.late
        ms.counters.guessed += st.guessed
        link.sent, link.lost, link.errors = link.sent + st.sent, link.lost + st.lost, link.errors + st.errors
        for name in ("queries", "replies", "denied", "late", "guessed", "sent", "lost", "errors", "n_events"):
            setattr(st, name, 0)

    def run(self, until: int) -> tuple[int, bytes, int, tuple[str, int]] | None:
        """Serve until host time `until`: None then, (RUN_EVENT, ...) on an FDIR event, or
        (RUN_HANDED, the datagram, its arrival (CLOCK_MONOTONIC ns), its sender)."""
        h = self.handed
        code = self.lib.snp_master_run(
            ctypes.byref(self.st), until, self.mono_of_real, self.spin_ns, self.lead_ns, self.buf, 2048, h
        )
        if code < 0:
            raise OSError(-code, os.strerror(-code))
        if code == RUN_UNTIL:
            return None
        if code == RUN_EVENT:
            return code, b"", 0, ("", 0)
        return code, self.buf.raw[: h.len], h.at, _sender(h)
