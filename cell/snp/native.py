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
import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

from cell.snp.modular import _IDS, JointModule

SOURCE = Path(__file__).with_name("cycle.c")
CFLAGS = ["-O2", "-shared", "-fPIC", "-Wall", "-Werror"]
RECORDS = 256
RUN_UNTIL, RUN_HANDED, RUN_RECORDS_FULL = 0, 1, 2
_I, _D = ctypes.c_int64, ctypes.c_double


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
        *((name, _D) for name in ("pos", "vel", "v_des", "torque")),
        *((name, _I) for name in ("next_start", "scheduled", "start", "deadline", "qid", "stage")),
        *((name, _I) for name in ("missed_now", "missed_ab", "missed_cd", "overruns", "sent", "lost")),
        *((name, _I) for name in ("errors", "late", "n_records")),
        ("records", (_I * 4) * RECORDS),
    ]


class Handed(ctypes.Structure):
    _fields_ = [(name, _I) for name in ("index", "len", "at", "ip", "port")]


class NativeUnavailable(RuntimeError):
    """No C compiler, or the build failed: the message says which."""


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "cell"


@functools.cache
def library() -> ctypes.CDLL:
    """The built library (built now if its cached copy is missing); NativeUnavailable if it cannot be."""
    source = SOURCE.read_bytes()
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        raise NativeUnavailable("no C compiler (cc, gcc or clang) on PATH")
    digest = hashlib.sha256(source + " ".join(CFLAGS).encode()).hexdigest()[:16]
    out = _cache_dir() / f"snp-cycle-{digest}.so"
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
            so = Path(tmp) / out.name
            cmd = [cc, *CFLAGS, "-o", str(so), str(SOURCE), "-lm"]
            done = subprocess.run(cmd, capture_output=True, text=True)
            if done.returncode != 0:
                raise NativeUnavailable(f"{cc} failed on {SOURCE.name}: {done.stderr.strip()[:2000]}")
            os.replace(so, out)  # (atomic: another process building it at once is harmless)
        for old in out.parent.glob("snp-cycle-*.so"):  # builds of earlier sources
            if old != out:
                old.unlink(missing_ok=True)
    lib = ctypes.CDLL(str(out))  # (a CDLL call releases the GIL)
    lib.snp_cycle_init.argtypes, lib.snp_cycle_init.restype = [ctypes.c_uint64], ctypes.c_int
    lib.snp_cycle_run.restype = ctypes.c_int
    lib.snp_cycle_run.argtypes = [
        ctypes.POINTER(ctypes.POINTER(ModuleState)), ctypes.c_int, _I, _I, _I, _I,
        ctypes.c_char_p, _I, ctypes.POINTER(Handed),
    ]  # fmt: skip
    size = lib.snp_cycle_init(0)
    if size != ctypes.sizeof(ModuleState):
        raise NativeUnavailable(f"module_t is {size} bytes in C, {ctypes.sizeof(ModuleState)} in ModuleState")
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

    def attach(self, fd: int, osc: Any, loss: float = 0.0) -> ModuleState:
        st = ModuleState(fd=fd, osc_origin=osc.origin, osc_offset=osc.offset_ns, osc_drift=osc.drift)
        st.loss = loss
        self._states[fd] = st
        return st

    def state(self, fd: int) -> ModuleState:
        return self._states[fd]

    def detach(self, fd: int) -> None:
        self._states.pop(fd, None)

    @staticmethod
    def push(st: ModuleState, m: JointModule, master: Any) -> None:
        """What the Python module decided since the last run: its servo, its configuration and,
        once it runs with transport snp, the cycle handed to C (where it then stays)."""
        s = m.servo
        st.servo_anchor, st.servo_base, st.servo_rate = s.anchor_raw, s.base, s.rate
        if st.active or m.state != "running" or m.transport != "snp" or master is None:
            return
        c = m.config
        assert c is not None
        ip = int.from_bytes(bytes(int(x) for x in master[0].split(".")), "big")
        st.master_ip, st.master_port, st.source_process = ip, master[1], m.source_process
        st.ids[:] = _IDS[m.joint]
        st.period_ns, st.phase_ns, st.budget_ns = c.period_ns, c.phase_ns, c.budget_ns
        st.pos, st.vel, st.v_des, st.torque = m.pos, m.vel, m.v_des, m.torque
        st.next_start, st.qid, st.stage = m.next_start, m._qid, 0
        st.active = 1

    @staticmethod
    def pull(st: ModuleState, m: JointModule, link: Any) -> None:
        """The C loop's records and counters into the module and its link (then zeroed in C)."""
        if not st.active:
            return
        n = st.n_records
        m.cycles.extend(tuple(st.records[i]) for i in range(n))
        m.missed["ab"] += st.missed_ab
        m.missed["cd"] += st.missed_cd
        m.overruns += st.overruns
        m.pos, m.vel, m.v_des, m.torque, m._qid = st.pos, st.vel, st.v_des, st.torque, st.qid
        link.sent, link.lost, link.errors = link.sent + st.sent, link.lost + st.lost, link.errors + st.errors
        for name in ("n_records", "missed_ab", "missed_cd", "overruns", "sent", "lost", "errors"):
            setattr(st, name, 0)

    def run(self, fds: list[int], until: int) -> tuple[int, int, bytes, int, tuple[str, int]] | None:
        """Run the cycles of the modules on these sockets until host time `until`; None then, or
        (code RUN_RECORDS_FULL, ...) when records must be taken, or (RUN_HANDED, the socket's fd,
        the datagram, its arrival (CLOCK_MONOTONIC ns), its sender)."""
        states = [self._states[fd] for fd in fds]
        arr = (ctypes.POINTER(ModuleState) * len(states))(*(ctypes.pointer(s) for s in states))
        h = self.handed
        code = self.lib.snp_cycle_run(
            arr, len(states), until, self.mono_of_real, self.spin_ns, self.lead_ns, self.buf, 2048, h
        )
        if code < 0:
            raise OSError(-code, os.strerror(-code))
        if code == RUN_UNTIL:
            return None
        if code == RUN_RECORDS_FULL:
            return code, -1, b"", 0, ("", 0)
        ip = ".".join(str((h.ip >> s) & 0xFF) for s in (24, 16, 8, 0))
        return code, fds[h.index], self.buf.raw[: h.len], h.at, (ip, h.port)
