"""The robots' tick in C (cell/robot/tick.c), built on first use and bound to a RobotGroup's arrays.

`NativeTick(group)` points C at the group's own numpy arrays (the drives', the backend's q and qd,
its MjData, the status records, the counters) and ticks them in place: what Python reads of the
group is what C wrote, and what Python sets (a hold, a URScript program's target, a silence) is what
C reads at its next tick.  Nothing is copied per tick.  `available()` says whether the library
builds here and, if not, why: the group then ticks in Python (the reference model C is held to).
"""

from __future__ import annotations

import ctypes
import functools
import os
import socket
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from cell.native import CFLAGS, build, unavailable
from cell.robot import datagram
from cell.robot.backends import KinematicArms, MujocoArms

if TYPE_CHECKING:
    from cell.robot.emulator import RobotGroup

HERE = Path(__file__).parent
SOURCE = HERE / "tick.c"
RT_THREAD = HERE.parent / "rt_thread.h"  # (its thread, created at its real-time priority)
VLEN, RX_BYTES = 8, 65536  # tick.c's
RING = 256  # ticks the ring keeps (0.5 s at 500 Hz): Python may fall that far behind and lose none
# GroupCounters' integer fields in tick.c's order (C_*); the rejects go to counters.rejected
COUNTERS = ("status_sent", "status_unsent", "late_sends", "commands")
REJECTS = ("length", "kind", "robot", "joint")
AFTER = ("protective_stops", "resumes", "ticks", "missed_ticks")
_I, _D, _P = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p


class GroupState(ctypes.Structure):
    """group_t of tick.c."""

    _fields_ = [
        *(
            (name, _I)
            for name in (
                *("n", "dof", "window_ticks", "watchdog", "shared", "nsock", "gso", "mujoco", "epfd"),
                *("tick_no", "n_stopping", "n_resuming"),
            )
        ),
        *((name, _D) for name in ("period", "scale", "h")),
        *((name, _P) for name in ("v_max", "a_max", "velocity", "target", "pending", "has_pending")),
        *((name, _P) for name in ("missed", "stopped", "armed", "holds", "scripted", "drive_counts")),
        *((name, _P) for name in ("q", "qd", "q_min", "q_max", "limit_hits")),
        *((name, _P) for name in ("model", "data", "step", "mulM")),
        *((name, _P) for name in ("qpos", "qvel", "ctrl", "applied", "bias", "gravcomp")),
        *((name, _P) for name in ("q_ref", "feedforward", "damping", "before", "mean", "accel", "tau")),
        ("fds", _P),
        ("row_of_fd", _P),
        ("max_fd", _I),
        ("addr", _P),
        ("addrlen", _I),
        *((name, _P) for name in ("ids", "row_of_id", "silent_until", "status", "seq", "counters")),
        *((name, _P) for name in ("answers", "answer_stats", "stopping", "resuming")),
        *((name, _P) for name in ("later_v", "later_has", "later_n", "flags", "rx", "tx")),
        *((name, _I) for name in ("origin_ns", "stop", "running", "tid", "wake_every", "wake_fd", "wakes")),
        *((name, _I) for name in ("ring_cap", "ring_head")),
        *((name, _P) for name in ("ring_tick", "ring_q", "ring_qd", "ring_target", "ring_velocity")),
        *((name, _P) for name in ("ring_stopped", "ring_flags", "lateness", "lateness_stats", "rt")),
        *((name, _P) for name in ("servo_q", "servo_ff", "servo_t", "servo_since", "servo_tau")),
        ("servo_extrapolate", _P),
        ("sent", _P),
    ]


@functools.cache
def _lib() -> ctypes.CDLL:
    lib = build("robot-tick", (SOURCE,), (RT_THREAD,), cflags=(*CFLAGS, "-ffp-contract=off"))
    p = ctypes.POINTER(GroupState)
    lib.rg_send.argtypes, lib.rg_send.restype = [p, _D], None
    lib.rg_after.argtypes, lib.rg_after.restype = [p, _I, _I], None
    lib.rg_step.argtypes, lib.rg_step.restype = [p, _D], None
    lib.rg_pack.argtypes, lib.rg_pack.restype = [p], None
    lib.rg_tick_timed.argtypes, lib.rg_tick_timed.restype = [p, _D, _I], _I
    lib.rg_init.argtypes, lib.rg_init.restype = [p], ctypes.c_int
    lib.rg_start.argtypes, lib.rg_start.restype = [p, ctypes.c_int], ctypes.c_int
    for name in ("rg_stop", "rg_lock", "rg_unlock", "rg_free"):
        getattr(lib, name).argtypes, getattr(lib, name).restype = [p], None
    return lib


@functools.cache
def mujoco_library() -> ctypes.CDLL:
    """The MuJoCo library the Python bindings loaded (the same one: its soname is already mapped)."""
    return ctypes.CDLL(next(Path(mujoco.__file__).parent.glob("libmujoco.so*")).as_posix())


def available() -> str:
    """ "" if the C tick builds here, else why not."""
    return unavailable(_lib)


def supports(group: RobotGroup) -> str:
    """ "" if this group can tick in C, else why not (a backend C does not step, a model it cannot)."""
    b = group.backend
    if type(b) not in (KinematicArms, MujocoArms):
        return f"{type(b).__name__} is stepped in Python"
    if isinstance(b, MujocoArms):
        m = b.model
        if not (m.nq == m.nv == m.nu == group.dof):
            return f"the model has nq={m.nq}, nv={m.nv}, nu={m.nu}: C steps one hinge and actuator a joint"
    return ""


def _ptr(a: np.ndarray) -> int:
    assert a.flags.c_contiguous, "the C tick needs contiguous arrays"
    return a.ctypes.data


class NativeTick:
    """One group's tick in C, on the group's own arrays."""

    def __init__(self, group: RobotGroup) -> None:
        lib = _lib()
        self.lib, self.group = lib, group
        d, b = group.drives, group.backend
        assert isinstance(b, KinematicArms | MujocoArms)  # (supports(group) said so)
        n, dof = group.n, group.dof
        self._keep: list[object] = []  # (arrays C points into that nothing else holds)
        st = self.state = GroupState(
            n=n,
            dof=dof,
            window_ticks=group.window_ticks,
            watchdog=d.watchdog,
            shared=int(group.shared),
            nsock=len(group.socks),
            gso=int(all(s.gso for s in group.senders)),
            epfd=group.poller.fileno(),
            tick_no=group.tick_no,
            period=group.period,
            scale=datagram.SCALE,
        )
        for name in ("v_max", "a_max", "velocity", "target", "pending", "has_pending", "missed"):
            setattr(st, name, _ptr(getattr(d, name)))
        for name in ("stopped", "armed", "holds", "scripted"):
            setattr(st, name, _ptr(getattr(d, name)))
        for name in ("servo_q", "servo_ff", "servo_t", "servo_since", "servo_tau", "servo_extrapolate"):
            setattr(st, name, _ptr(getattr(d, name)))
        st.drive_counts = _ptr(d.counts)
        st.q, st.qd = _ptr(b.q), _ptr(b.qd)
        st.q_min, st.q_max = self._own(b.q_min), self._own(b.q_max)
        self.limit_hits = np.zeros(1, np.int64)
        st.limit_hits = _ptr(self.limit_hits)
        size = n * dof
        for name, k in (("before", size), ("mean", size), ("accel", 2 * size), ("tau", max(dof, 1))):
            setattr(st, name, self._own(np.zeros(k)))
        if isinstance(b, MujocoArms):
            self._bind_mujoco(b)
        # sockets: each robot's, the data plane's address, who a socket or a robot id is
        fds = np.array([s.fileno() for s in group.socks] or [0], np.int32)
        st.fds = self._own(fds)
        st.max_fd = int(fds.max())
        row_of_fd = np.full(st.max_fd + 1, -1, np.int32)
        for s, row in ((s, group.row_of_fd[s.fileno()]) for s in group.socks):
            row_of_fd[s.fileno()] = row
        st.row_of_fd = self._own(row_of_fd)
        addr = self._own(np.frombuffer(_sockaddr(group.dataplane), np.uint8).copy())
        st.addr, st.addrlen = addr, len(_sockaddr(group.dataplane))
        st.ids = self._own(group.ids)
        row_of_id = group.row_of_id if group.shared else np.full(1, -1, np.int64)
        st.row_of_id = self._own(row_of_id)
        st.silent_until, st.status, st.seq = _ptr(group.silent_until), _ptr(group.status), _ptr(group.seq)
        self.counters = np.zeros(len(COUNTERS) + len(REJECTS) + len(AFTER), np.int64)
        self._seen = self.counters.copy()
        st.counters = _ptr(self.counters)
        c = group._counters
        st.answers, st.answer_stats = _ptr(c.answers.counts), _ptr(c.answers.stats)
        self.stopping, self.resuming = np.zeros(n, np.int64), np.zeros(n, np.int64)
        st.stopping, st.resuming = _ptr(self.stopping), _ptr(self.resuming)
        st.later_v = self._own(np.zeros(size))
        st.later_has = self._own(np.zeros(size, np.uint8))
        st.later_n = self._own(np.zeros(n, np.int64))
        st.flags = self._own(np.zeros(n, np.uint8))
        st.rx = self._own(np.zeros(VLEN * RX_BYTES, np.uint8))
        st.tx = self._own(np.zeros(max(size, 1) * datagram.SIZE, np.uint8))
        # the thread's ring: every tick's state, for Python to read at its own pace
        st.ring_cap, st.wake_fd = RING, -1
        self.ring_tick = np.full(RING, -1, np.int64)
        self.ring_q, self.ring_qd = np.zeros((RING, n, dof)), np.zeros((RING, n, dof))
        self.ring_target, self.ring_velocity = np.zeros((RING, n, dof)), np.zeros((RING, n, dof))
        self.ring_stopped, self.ring_flags = np.zeros((RING, n), bool), np.zeros((RING, n), np.uint8)
        for name in ("ring_tick", "ring_q", "ring_qd", "ring_target", "ring_velocity"):
            setattr(st, name, _ptr(getattr(self, name)))
        st.ring_stopped, st.ring_flags = _ptr(self.ring_stopped), _ptr(self.ring_flags)
        st.lateness, st.lateness_stats = _ptr(c.lateness.counts), _ptr(c.lateness.stats)
        st.sent = _ptr(group.sent_ns)
        self._ref = ctypes.byref(st)
        rc = lib.rg_init(self._ref)
        if rc:
            raise OSError(rc, f"cannot make the group's lock: {os.strerror(rc)}")
        self.lock = NativeLock(lib, self._ref)
        d.lock = self.lock  # (what Python changes of the drives, between two ticks of the thread)

    def __del__(self) -> None:
        if getattr(self, "state", None) is not None and self.state.rt:
            self.lib.rg_free(self._ref)  # (stops the thread if it still runs)

    def _own(self, a: np.ndarray) -> int:
        a = np.ascontiguousarray(a)
        self._keep.append(a)
        return _ptr(a)

    def _bind_mujoco(self, b: MujocoArms) -> None:
        st, mj = self.state, mujoco_library()
        st.mujoco, st.h = 1, b.model.opt.timestep
        st.model = b.model._address
        st.step = ctypes.cast(mj.mj_step, ctypes.c_void_p).value
        st.mulM = ctypes.cast(mj.mj_mulM, ctypes.c_void_p).value
        n = len(b.data)
        arrays = (ctypes.c_void_p * n)(*(d._address for d in b.data))
        self._keep.append(arrays)
        st.data = ctypes.addressof(arrays)
        for name, field in (
            ("qpos", "qpos"),
            ("qvel", "qvel"),
            ("ctrl", "ctrl"),
            ("applied", "qfrc_applied"),
            ("bias", "qfrc_bias"),
            ("gravcomp", "qfrc_gravcomp"),
        ):
            ptrs = (ctypes.c_void_p * n)(*(_ptr(getattr(d, field)) for d in b.data))
            self._keep.append(ptrs)
            setattr(st, name, ctypes.addressof(ptrs))
        st.q_ref = _ptr(b.q_ref)
        st.feedforward = self._own(np.asarray(b.feedforward, np.float64))
        st.damping = self._own(np.asarray(b.damping, np.float64))

    # --- one tick (RobotGroup.tick's halves) ----------------------------------------------------

    def send(self, deadline: float) -> None:
        self.lib.rg_send(self._ref, deadline)

    def after(self, cutoff_ns: int, periods: int) -> tuple[np.ndarray, np.ndarray]:
        """Take, step, pack; the rows that stopped and resumed."""
        st = self.state
        self.lib.rg_after(self._ref, cutoff_ns, periods)
        g = self.group
        g.tick_no = st.tick_no
        if isinstance(g.backend, KinematicArms):
            g.backend.limit_hits = int(self.limit_hits[0])
        return self.stopping[: st.n_stopping].copy(), self.resuming[: st.n_resuming].copy()

    # --- the tick in a thread of its own ----------------------------------------------------------

    def start(self, origin_ns: int, wake_fd: int, wake_every: int, priority: int = 0) -> int:
        """Tick in C's own thread from origin_ns (CLOCK_MONOTONIC), writing `wake_fd` (an eventfd) on
        every `wake_every`-th tick and on each tick a robot stopped or resumed in, at SCHED_FIFO
        `priority` (0, or refused: as this thread runs); its thread id."""
        st = self.state
        st.origin_ns, st.wake_fd, st.wake_every = origin_ns, wake_fd, wake_every
        rc = self.lib.rg_start(self._ref, priority)
        if rc:
            raise OSError(rc, f"cannot start the robots' tick thread: {os.strerror(rc)}")
        deadline = time.monotonic() + 1.0
        while not st.tid and time.monotonic() < deadline:  # (it runs within microseconds)
            time.sleep(0.0005)
        return int(st.tid)

    def stop(self) -> None:
        self.lib.rg_stop(self._ref)
        st = self.state
        self.group.tick_no = st.tick_no

    def pull(self, into) -> None:
        """C's counts since the last pull into the group's GroupCounters (a pull at any time is safe:
        C only ever adds)."""
        now = self.counters.copy()
        delta = (now - self._seen).tolist()
        self._seen = now
        k = 0
        for name in COUNTERS:
            setattr(into, name, getattr(into, name) + delta[k])
            k += 1
        for name in REJECTS:
            into.rejected[name] += delta[k]
            k += 1
        for name in AFTER:
            setattr(into, name, getattr(into, name) + delta[k])
            k += 1
        into.commands_ignored = self.group.drives.ignored


class NativeLock:
    """The group's lock (a priority-inheriting mutex the C tick holds while it runs), as a context
    manager; a ctypes call releases the GIL while it waits."""

    def __init__(self, lib: ctypes.CDLL, ref: object) -> None:
        self.lib, self.ref = lib, ref

    def __enter__(self) -> None:
        self.lib.rg_lock(self.ref)

    def __exit__(self, *exc: object) -> None:
        self.lib.rg_unlock(self.ref)


def _sockaddr(addr: tuple[str, int]) -> bytes:
    """A struct sockaddr_in(6) for sendto."""
    host, port = addr
    if ":" in host:
        raw = socket.inet_pton(socket.AF_INET6, host)
        return (
            socket.AF_INET6.to_bytes(2, sys.byteorder) + port.to_bytes(2, "big") + bytes(4) + raw + bytes(4)
        )
    raw = socket.inet_pton(socket.AF_INET, socket.gethostbyname(host))
    return socket.AF_INET.to_bytes(2, sys.byteorder) + port.to_bytes(2, "big") + raw + bytes(8)
