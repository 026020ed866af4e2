"""The XDP data plane's BPF object: loaded, its maps mapped into this process as numpy arrays.

The maps are BPF_F_MMAPABLE arrays, so the control plane reads and writes the very memory the
program matches against, with numpy (the same Tables and Pipeline code as the numpy backend
works on them).  The dtypes below mirror the C structs of dataplane.bpf.c field by field; the
loader checks their sizes against the object's BTF-sized maps.
"""

from __future__ import annotations

import contextlib
import ctypes
import mmap
import os
import socket
import struct
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cell.config import XDP_OBJECT
from cell.dataplane.approx import entries_per_sign
from cell.dataplane.xdp import libbpf
from cell.dataplane.xdp.libbpf import BpfError

OBJECT = XDP_OBJECT
MAX_JOINTS = 12  # the C program's TP width
MAX_ENTITIES = 4096
XDP_DROP, XDP_PASS, XDP_TX = 1, 2, 3
SKB_MODE = 1 << 1  # XDP_FLAGS_SKB_MODE: generic XDP, the mode veth and lo offer here
GATE_WAIT_S = 0.05  # a packet in flight takes microseconds; this long means something is wrong

ROBOT = np.dtype(
    {
        "names": [
            "entity",
            "joint0",
            "joints",
            "stale_periods",
            "quiet_ns",
            "status_ns",
            "status_seq",
            "pin_addr",
            "pin_port",
            "pinned",
            "stop",
        ],
        "formats": ["<i4", "<i4", "<i8", "<i8", "<i8", "<i8", "<i8", "<u4", "<u2", "u1", "?"],
        "offsets": [0, 4, 8, 16, 24, 32, 40, 48, 52, 54, 55],
        "itemsize": 56,
    }
)
STATUS = np.dtype([("pos", "<i8", MAX_JOINTS), ("vel", "<i8", MAX_JOINTS), ("cmd", "<i8", MAX_JOINTS)])
ENTITY = np.dtype(
    {
        "names": ["tp", "stalled", "dropped_why", "next_time", "stall_ns", "dropped_ns"],
        "formats": ["<i4", "?", "i1", "<i8", "<i8", "<i8"],
        "offsets": [0, 4, 5, 8, 16, 24],
        "itemsize": 32,
    }
)
ROW = np.dtype(
    [
        ("next_row", "<i4"),
        ("switch_row", "<i4"),
        ("duration", "<i8"),
        ("trg_pos", "<i8", MAX_JOINTS),
        ("trg_vel", "<i8", MAX_JOINTS),
    ]
)
LIMIT = np.dtype(
    [("limit", "<i8"), ("neg", "<i8")] + [(f, "<i8", 64) for f in ("hi_v", "hi_m", "lo_v", "lo_m")]
)
GLOBALS = np.dtype(
    [
        ("listen_addr", "<u4"),
        ("listen_port", "<u2"),
        ("pad0", "<u2"),
        ("clock_ns", "<i8"),
        ("n_bits", "<u4"),
        ("joints", "<u4"),
        ("max_joints", "<u4"),
        ("stopping", "<u4"),
        ("entries_per_sign", "<u8"),
        ("bank_size", "<u8"),
        ("closed", "<u4"),
        ("inflight", "<u4"),
        ("stop_ramp", "<i8", MAX_JOINTS),
    ]
)
COUNTERS = (
    "packets",
    "holds",
    "steps",
    "resubmits",
    "stalls",
    "limited",
    "stop_commands",
    "dropped",
    "rejected.length",
    "rejected.kind",
    "rejected.joint",
    "rejected.spoofed",
    "rejected.batch",
    "held",
    "commands_out",
    "datagrams",
)


MAPS = ("robots", "status", "entities", "rows", "transform", "limits", "globals", "counters")
PROGRAMS = ("velocity_control", "gate", "reflect")


@dataclass(frozen=True)
class Resources:
    """What a loaded program takes of the kernel (Fig. 13a-b's resources, for this target): each
    map's entries and locked memory, each program's instructions (translated, and as many as the
    verifier walked through its paths) and its JIT-compiled size."""

    maps: dict[str, tuple[int, int]]  # name -> (entries, bytes)
    programs: dict[str, tuple[int, int, int]]  # name -> (instructions, verified, JIT bytes)

    @property
    def map_bytes(self) -> int:
        return sum(b for _, b in self.maps.values())


class Gate:
    """The control plane's gate over a packet path in C reading mapped tables (the XDP program's,
    the native data plane's: globals.closed and globals.inflight, each side's locked add the fence),
    and what the control plane knows of its flips; a program says how it turns the gate (_gate)."""

    gate_error: type[Exception] = BpfError
    globals: np.void

    def _init_gate(self, n_bits: int, joints: int, eps: int) -> None:
        """The constants the packet path reads of the tables, and no flip yet."""
        g = self.globals
        g["n_bits"], g["joints"], g["max_joints"] = n_bits, joints, MAX_JOINTS
        g["entries_per_sign"], g["bank_size"] = eps, joints * 2 * eps
        self.gates = 0  # how often the control plane closed the gate (each a flip)
        self.closed_ns: list[int] = []  # how long each closing lasted (recent ones)
        self._closed_at = 0
        self._priority: int | None = None  # the thread's own while it holds the gate at the ceiling

    def _gate(self, op: int) -> None:
        raise NotImplementedError

    def close_gate(self) -> None:
        """From now until open_gate(), statuses are answered with each joint's last command and
        nothing reads the tables; returns once no packet is still in the program.

        A real-time control plane holds the gate at a priority ceiling (just under the kernel's
        own top), so that a higher-priority process on its core (the robots) cannot stretch a
        flip of tens of microseconds into milliseconds of held statuses (a priority inversion:
        the packet path waits on the gate's holder)."""
        self._raise_priority()
        try:
            self._gate(1)
        except BaseException:
            self._restore_priority()
            raise
        self.gates += 1
        self._closed_at = time.perf_counter_ns()
        deadline = time.monotonic() + GATE_WAIT_S
        while self.globals["inflight"]:
            if time.monotonic() > deadline:
                self._gate(0)
                self._restore_priority()
                raise self.gate_error(f"a packet stayed in the packet path for {GATE_WAIT_S * 1e3:.0f} ms")

    def open_gate(self) -> None:
        try:
            self._gate(0)
            self.closed_ns.append(time.perf_counter_ns() - self._closed_at)
            del self.closed_ns[:-4096]
        finally:
            self._restore_priority()

    def _raise_priority(self) -> None:
        self._priority = None
        with contextlib.suppress(OSError, AttributeError):
            policy = os.sched_getscheduler(0)
            if policy in (os.SCHED_FIFO, os.SCHED_RR):
                was = os.sched_getparam(0).sched_priority
                os.sched_setparam(0, os.sched_param(max(was, os.sched_get_priority_max(policy) - 1)))
                self._priority = was

    def _restore_priority(self) -> None:
        if self._priority is not None:
            with contextlib.suppress(OSError):
                os.sched_setparam(0, os.sched_param(self._priority))
            self._priority = None


class XdpProgram(Gate):
    """The velocity-control program and its maps; close() unloads it (and detaches it if attached)."""

    def __init__(self, capacity: int, n_bits: int, joints: int, obj: Path = OBJECT) -> None:
        if not obj.exists():
            raise BpfError(f"{obj} is not built: run `make bpf` (needs clang; `make test` builds it as root)")
        bpf = libbpf.lib()
        self._bpf = bpf
        self.capacity, self.joints = capacity, joints
        self.eps = entries_per_sign(n_bits)
        self.n_bits = n_bits
        self._maps: list[mmap.mmap] = []
        self.ifindex: int | None = None
        self.obj: int | None = libbpf.pointer(
            bpf.bpf_object__open_file(str(obj).encode(), None), f"opening {obj}"
        )
        try:
            sizes = {"rows": capacity, "transform": 3 * joints * 2 * self.eps}
            for name, n in sizes.items():
                libbpf.check(bpf.bpf_map__set_max_entries(self._map(name), n), f"sizing map {name}")
            libbpf.check(bpf.bpf_object__load(self.obj), f"loading {obj.name} (the verifier's log follows)")
            self.robots = self._mmap("robots", ROBOT)
            self.status = self._mmap("status", STATUS)
            self.entities = self._mmap("entities", ENTITY)
            self.rows = self._mmap("rows", ROW)
            self.transform = self._mmap("transform", np.dtype("<i8"))
            self.limits = self._mmap("limits", LIMIT)
            self.globals = self._mmap("globals", GLOBALS)[0]
            self.prog_fd = self._prog("velocity_control")
            self.gate_fd = self._prog("gate")
            self.reflect_fd = self._prog("reflect")
            self.counters_fd = bpf.bpf_map__fd(self._map("counters"))
            self.cpus = libbpf.check(bpf.libbpf_num_possible_cpus(), "counting CPUs")
        except BaseException:
            self.close()
            raise
        self._init_gate(n_bits, joints, self.eps)

    def resources(self) -> Resources:
        maps = {}
        for name in MAPS:
            m = self._map(name)
            info = libbpf.fdinfo(self._bpf.bpf_map__fd(m))
            maps[name] = (int(self._bpf.bpf_map__max_entries(m)), int(info.get("memlock", 0)))
        programs = {}
        for name in PROGRAMS:
            fd = self._prog(name)
            xlated, jited = libbpf.prog_sizes(fd)
            programs[name] = (xlated // 8, int(libbpf.fdinfo(fd).get("verified_insns", -1)), jited)
        return Resources(maps, programs)

    def _map(self, name: str) -> int:
        return libbpf.pointer(self._bpf.bpf_object__find_map_by_name(self.obj, name.encode()), f"map {name}")

    def _prog(self, name: str) -> int:
        prog = libbpf.pointer(self._bpf.bpf_object__find_program_by_name(self.obj, name.encode()), name)
        return libbpf.check(self._bpf.bpf_program__fd(prog), f"program {name}")

    def _mmap(self, name: str, dtype: np.dtype) -> np.ndarray:
        m = self._map(name)
        size, n = self._bpf.bpf_map__value_size(m), self._bpf.bpf_map__max_entries(m)
        if size != dtype.itemsize:
            raise BpfError(f"map {name}: {size}-byte values, this loader expects {dtype.itemsize}")
        length = -(-((size + 7) // 8 * 8 * n) // mmap.PAGESIZE) * mmap.PAGESIZE
        mem = mmap.mmap(self._bpf.bpf_map__fd(m), length, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
        self._maps.append(mem)
        return np.frombuffer(mem, dtype, count=n)

    # --- the packet path, run on a given packet (tests, differential checks) ------------------

    def run(self, packet: bytes) -> tuple[int, bytes]:
        """The program's verdict on one Ethernet frame, and the frame as it leaves."""
        return libbpf.test_run(self.prog_fd, packet, max(len(packet), 64) + 256)

    def answer(self, payload: bytes, src: tuple[str, int]) -> bytes | None:
        """The program's answer to a status datagram that reached user space instead of it (the
        program was detached): the same frame the kernel would have seen, run through the program in
        the kernel (BPF_PROG_TEST_RUN, so its maps and counters are the real ones); the commands'
        payload, or None where the program drops it (malformed, spoofed)."""
        g = self.globals
        dst = int(g["listen_addr"]).to_bytes(4, "little")
        udp = struct.pack("!HHHH", src[1], socket.ntohs(int(g["listen_port"])), 8 + len(payload), 0)
        ip = struct.pack(
            "!BBHHHBBH4s4s", 0x45, 0, 28 + len(payload), 0, 0, 64, 17, 0, socket.inet_aton(src[0]), dst
        )
        frame = bytes(6) + bytes(6) + b"\x08\x00" + ip + udp + payload
        verdict, out = self.run(frame)
        if verdict != XDP_TX:
            return None
        return out[14 + 20 + 8 : 14 + 20 + 8 + len(payload)]

    def _gate(self, op: int) -> None:
        verdict, _ = libbpf.test_run(self.gate_fd, bytes([op]) + bytes(63), 128)
        if verdict != XDP_PASS:
            raise BpfError(f"gate program answered {verdict}")

    # --- counters ------------------------------------------------------------------------------

    def counters(self) -> dict[str, int]:
        """Every counter of the program, summed over the CPUs.  Read last to first while packets go on
        being counted: a count of what went out (commands_out, listed after what came in) is read
        before the counts of what it answered, so it is never more than they (read first to last, a
        CI run's packets_in was 9,624 to 9,630 commands out)."""
        out: dict[str, int] = {}
        vals = (ctypes.c_uint64 * self.cpus)()
        for i, name in reversed(list(enumerate(COUNTERS))):
            key = ctypes.c_uint32(i)
            libbpf.check(
                self._bpf.bpf_map_lookup_elem(self.counters_fd, ctypes.byref(key), vals), f"counter {name}"
            )
            out[name] = int(sum(vals))
        return {name: out[name] for name in COUNTERS}

    # --- attaching -----------------------------------------------------------------------------

    def attach(self, ifindex: int, reflect: bool = False) -> int:
        """Attach in generic (skb) mode to an interface of the calling thread's network namespace;
        reflect: the bare reflector instead (a benchmark's baseline).  The program's id as attached."""
        fd = self.reflect_fd if reflect else self.prog_fd
        libbpf.check(self._bpf.bpf_xdp_attach(ifindex, fd, SKB_MODE, None), "attaching XDP")
        self.ifindex = ifindex
        return self.attached()

    def attached(self) -> int:
        """The id of the program attached (generic mode) to our interface, 0 if none (the calling
        thread in the interface's network namespace)."""
        if self.ifindex is None:
            return 0
        prog_id = ctypes.c_uint32(0)
        libbpf.check(self._bpf.bpf_xdp_query_id(self.ifindex, SKB_MODE, ctypes.byref(prog_id)), "XDP query")
        return prog_id.value

    def detach(self) -> None:
        """(The calling thread in the interface's network namespace: an ifindex is per namespace.)"""
        if self.ifindex is not None:
            self._bpf.bpf_xdp_detach(self.ifindex, SKB_MODE, None)
            self.ifindex = None

    def close(self) -> None:
        for name in ("robots", "status", "entities", "rows", "transform", "limits", "globals"):
            self.__dict__.pop(name, None)  # (the views go before the memory they view)
        for mem in self._maps:
            with contextlib.suppress(BufferError):  # a view still held elsewhere: it goes with that
                mem.close()
        self._maps.clear()
        if getattr(self, "obj", None):
            self._bpf.bpf_object__close(self.obj)
            self.obj = None
