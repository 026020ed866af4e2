"""The user-space data plane in C (backend "native"): the XDP program's own source run over a UDP
socket in a thread of its own (cell/dataplane/native.c), its maps memory this process owns.

`NativeProgram` has the XdpProgram's interface (its maps as numpy arrays of the same dtypes, the
gate, the counters, `answer`), so the XDP backend's Tables and Pipeline (cell.dataplane.xdp.backend)
are its control plane unchanged: a TP, a switch, a register, a drop or a stop is written to the very
memory the packet path reads, behind the same gate.  `NativeServer` is the packet path: recvmmsg,
Algorithms 1 and 2 per burst, sendmmsg, with no Python per packet.  The library is built with the
system's C compiler on first use (cell.native); `available()` says whether that works here.
"""

from __future__ import annotations

import asyncio
import ctypes
import functools
import logging
import os
import socket
import time
from pathlib import Path

import numpy as np

from cell import meter, sched
from cell.config import CellConfig, parse_host_port
from cell.dataplane.approx import entries_per_sign
from cell.dataplane.plane import CONTROL_PRIORITY, MappedDataPlane, Pins
from cell.dataplane.xdp.program import (
    COUNTERS,
    ENTITY,
    GLOBALS,
    LIMIT,
    MAX_ENTITIES,
    MAX_JOINTS,
    ROBOT,
    ROW,
    STATUS,
    Gate,
)
from cell.native import NativeUnavailable, build, unavailable
from cell.robot import datagram, udp

HERE = Path(__file__).parent
SOURCE = HERE / "native.c"
BPF_SOURCE = HERE / "xdp" / "dataplane.bpf.c"
RT_THREAD = HERE.parent / "rt_thread.h"
HANDLED, HELD, BAD = 0, 1, 2  # handle()'s verdicts (dataplane.bpf.c)
BATCH_BINS = 1024  # native.c's: each wake-up's handling time in 1 us bins
MAPS = (
    *("robots", "status", "entities", "rows", "transform"),
    *("limits", "globals", "counters", "scratches", "marks"),
)
_U64, _P = ctypes.c_uint64, ctypes.c_void_p
log = logging.getLogger("cell.dataplane")


class _Map(ctypes.Structure):
    _fields_ = [("base", _P), ("max", _U64), ("size", _U64)]


class NativeMaps(ctypes.Structure):
    """struct maps of native.c."""

    _fields_ = [(name, _Map) for name in MAPS]


class ServerState(ctypes.Structure):
    """The head of struct server (native.c); its buffers follow, sized by dp_server_size()."""

    _fields_ = [
        ("maps", _P),
        *(
            (name, ctypes.c_int64)
            for name in (
                *("fd", "stop", "running", "wakeups", "bursts", "answered", "unsent", "batch_ns_max"),
                "tid",
            )
        ),
        ("batch_us", ctypes.c_int64 * BATCH_BINS),
    ]


@functools.cache
def _lib() -> tuple[ctypes.CDLL, int, int]:
    """The library, and the sizes of native.c's scratch and mark records."""
    lib = build("dataplane", (SOURCE,), (BPF_SOURCE, RT_THREAD))
    lib.dp_payload.argtypes = [_P, _P, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint16]
    lib.dp_payload.restype = ctypes.c_int
    lib.dp_gate.argtypes, lib.dp_gate.restype = [_P, ctypes.c_int], None
    lib.dp_serve.argtypes, lib.dp_serve.restype = [_P], ctypes.c_int64
    lib.dp_start.argtypes, lib.dp_start.restype = [_P, ctypes.c_int], ctypes.c_int
    lib.dp_stop.argtypes, lib.dp_stop.restype = [_P], None
    lib.dp_server_size.argtypes, lib.dp_server_size.restype = [], _U64
    lib.dp_sizes.argtypes, lib.dp_sizes.restype = [_P], None
    sizes = (_U64 * 9)()
    lib.dp_sizes(sizes)
    want = (ROBOT, STATUS, ENTITY, ROW, LIMIT, GLOBALS)
    for dtype, size in zip(want, sizes[:6], strict=True):
        if dtype.itemsize != size:
            raise NativeUnavailable(f"native.c's maps hold {size}-byte values where the dtypes say {dtype}")
    if sizes[8] != len(COUNTERS):
        why = f"native.c counts {sizes[8]} counters, cell.dataplane.xdp.program names {len(COUNTERS)}"
        raise NativeUnavailable(why)
    return lib, int(sizes[6]), int(sizes[7])


def available() -> str:
    """ "" if the native data plane builds here, else why not."""
    return unavailable(_lib)


class NativeProgram(Gate):
    """The maps of one native data plane (XdpProgram's interface), and the C that runs over them."""

    gate_error = RuntimeError

    def __init__(self, capacity: int, n_bits: int, joints: int) -> None:
        self.lib, scratch_size, mark_size = _lib()
        self.capacity, self.joints, self.n_bits = capacity, joints, n_bits
        self.eps = entries_per_sign(n_bits)
        self.robots = np.zeros(1 << 16, ROBOT)
        self.status = np.zeros(1 << 16, STATUS)
        self.entities = np.zeros(MAX_ENTITIES, ENTITY)
        self.rows = np.zeros(capacity, ROW)
        self.transform = np.zeros(3 * joints * 2 * self.eps, np.int64)
        self.limits = np.zeros(MAX_JOINTS, LIMIT)
        self._globals = np.zeros(1, GLOBALS)
        self.globals = self._globals[0]
        self._counters = np.zeros(len(COUNTERS), np.uint64)
        self._retired: list[np.ndarray] = []
        self._scratch = np.zeros(scratch_size, np.uint8)
        self._marks = np.zeros(MAX_ENTITIES * mark_size, np.uint8)
        self.maps = NativeMaps()
        for name, arr, n, size in (
            ("robots", self.robots, 1 << 16, ROBOT.itemsize),
            ("status", self.status, 1 << 16, STATUS.itemsize),
            ("entities", self.entities, MAX_ENTITIES, ENTITY.itemsize),
            ("rows", self.rows, capacity, ROW.itemsize),
            ("transform", self.transform, self.transform.size, 8),
            ("limits", self.limits, MAX_JOINTS, LIMIT.itemsize),
            ("globals", self._globals, 1, GLOBALS.itemsize),
            ("counters", self._counters, len(COUNTERS), 8),
            ("scratches", self._scratch, 1, scratch_size),
            ("marks", self._marks, MAX_ENTITIES, mark_size),
        ):
            setattr(self.maps, name, _Map(arr.ctypes.data, n, size))
        self._ref = ctypes.addressof(self.maps)
        self._init_gate(n_bits, joints, self.eps)

    def fit(self, n_bits: int) -> None:
        """Transform tables of `n_bits` (the gate closed: nothing reads them meanwhile): the memory is
        this process's, so new controller constants need no restart, unlike an XDP program's."""
        if n_bits == self.n_bits:
            return
        self._retired.append(self.transform)  # (a packet that read its address before the gate shut)
        self.n_bits, self.eps = n_bits, entries_per_sign(n_bits)
        self.transform = np.zeros(3 * self.joints * 2 * self.eps, np.int64)
        self.maps.transform = _Map(self.transform.ctypes.data, self.transform.size, 8)
        g = self.globals
        g["n_bits"], g["entries_per_sign"], g["bank_size"] = n_bits, self.eps, self.joints * 2 * self.eps

    # --- the packet path on a given payload (tests, differential checks) ------------------------

    def answer(self, payload: bytes, src: tuple[str, int]) -> bytes | None:
        """The commands the packet path makes of one datagram's records from `src`, or None where it
        drops them (malformed, a bad record, spoofed)."""
        buf = (ctypes.c_uint8 * max(len(payload), 1)).from_buffer_copy(payload or b"\0")
        addr = int.from_bytes(socket.inet_aton(src[0]), "little")  # (network order in memory)
        verdict = self.lib.dp_payload(self._ref, buf, len(payload), addr, socket.htons(src[1]))
        return None if verdict in (-1, BAD) else bytes(buf)[: len(payload)]

    def _gate(self, op: int) -> None:
        self.lib.dp_gate(self._ref, op)

    def counters(self) -> dict[str, int]:
        return dict(zip(COUNTERS, self._counters.tolist(), strict=True))

    def close(self) -> None:
        """(Memory this process owns: nothing to unload.)"""


class NativeServer:
    """The packet path over one socket, in a C thread: every status answered as it comes."""

    def __init__(self, program: NativeProgram, sock: socket.socket) -> None:
        lib = self.lib = program.lib
        self.program, self.sock = program, sock
        self._mem = np.zeros(int(lib.dp_server_size()), np.uint8)
        self.state = ServerState.from_address(self._mem.ctypes.data)
        self.state.maps = program._ref
        self.state.fd = sock.fileno()
        self._ref = ctypes.addressof(self.state)

    def serve(self) -> int:
        """What waits now, handled in this thread (no serving thread running); bursts handled."""
        return int(self.lib.dp_serve(self._ref))

    def start(self, priority: int = 0) -> None:
        """Serve in a thread of C's own, at SCHED_FIFO `priority` (0: as this thread runs)."""
        rc = self.lib.dp_start(self._ref, priority)
        if rc:
            raise OSError(rc, f"cannot start the data plane's thread: {os.strerror(rc)}")
        deadline = time.monotonic() + 1.0
        while not self.state.tid and time.monotonic() < deadline:  # (it runs within microseconds)
            time.sleep(0.0005)

    def stop(self) -> None:
        self.lib.dp_stop(self._ref)

    def counters(self) -> dict[str, float]:
        s = self.state
        hist = np.frombuffer(s.batch_us, np.int64)
        out = {}
        if n := int(hist.sum()):  # (as the numpy data plane's: what one wake-up's batch took)
            cum = np.cumsum(hist)
            out["batch_p50_us"] = float(np.searchsorted(cum, 0.5 * n) + 1)
            out["batch_p99_us"] = float(np.searchsorted(cum, 0.99 * n) + 1)
        return out | {
            "native.wakeups": s.wakeups,
            "native.bursts": s.bursts,
            "native.answered": s.answered,
            "native.unsent": s.unsent,
            "native.batch_us_max": s.batch_ns_max / 1e3,
        }


class NativeDataPlane(MappedDataPlane):
    """The packet path in C in a thread of this process (NativeServer), on the listen socket: the only
    thread left at the process's real-time priority (sched.hand_over); this one is the control plane
    around it, as for the XDP program."""

    prefix = "native."

    def _program(self, config: CellConfig) -> NativeProgram:
        dp = config.dataplane
        return NativeProgram(dp.capacity, dp.n_bits, len(dp.c1))

    def _open(self, config: CellConfig) -> None:
        dp = config.dataplane
        self.robot_addr = Pins(self.program.robots)  # (pinned by the packet path, in its maps)
        self.sock = udp.open_socket(*parse_host_port(dp.listen))
        self.sender = udp.Sender(self.sock, datagram.SIZE)
        self.server = NativeServer(self.program, self.sock)

    def handle(self) -> int:
        """(No serving thread: tests.)  Every burst waiting, answered now; how many."""
        return self.server.serve()

    async def run(self) -> None:
        """Serve in C until cancelled; this process's other threads under its real-time priority."""
        # the control plane under the packet path, over every normal process (CONTROL_PRIORITY); set
        # before the loop starts, which is created at its own priority (sched.place_loops)
        problems = sched.rest_at(CONTROL_PRIORITY)
        self.server.start(sched.LOOP_PRIORITY)
        try:
            tid = int(self.server.state.tid)
            for problem in problems + sched.hand_over(tid):
                log.warning("%s", problem)
            if tid in sched.RT_THREADS:
                meter.watch_thread(tid)
            await asyncio.Future()  # (until cancelled)
        finally:
            self.server.stop()

    def close(self) -> None:
        self.server.stop()
        self.sock.close()

    def counters(self) -> dict[str, float]:
        out = super().counters()
        out.update(self.server.counters())
        out["unsent"] = self.unsent + self.server.state.unsent
        return out
