"""The XDP backend's switch: a network namespace joined to the host by a veth pair.

The launcher creates it before any service starts (robots bind the host's end) and removes it when
the cell stops; the data plane attaches its program to the namespace's end.  Work inside the
namespace runs on a thread that entered it (setns changes only the calling thread's namespace).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import logging
import os
import subprocess
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

from cell.config import XdpConfig, xdp_missing

log = logging.getLogger(__name__)

T = TypeVar("T")
CLONE_NEWNET = 0x40000000


class SwitchError(RuntimeError):
    """The XDP backend cannot run here; the message says what is missing."""


def _ip(*args: str) -> None:
    done = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)
    if done.returncode:
        raise SwitchError(f"ip {' '.join(args)}: {done.stderr.strip()}")


OWNERS = Path("/run/cell-switches")  # <netns>: the pid of the launcher that made that switch


def remove(cfg: XdpConfig) -> None:
    """The namespace and the veth pair gone (whatever is left of them), and its owner's record."""
    subprocess.run(["ip", "netns", "del", cfg.netns], capture_output=True, timeout=10)
    subprocess.run(["ip", "link", "del", f"{cfg.veth}0"], capture_output=True, timeout=10)
    (OWNERS / cfg.netns).unlink(missing_ok=True)


def owner(netns: str) -> int | None:
    """The live process that made the switch `netns`; None if it is gone (killed: its switch was
    left behind) or the namespace is not one a launcher recorded."""
    try:
        pid = int((OWNERS / netns).read_text())
        os.kill(pid, 0)
    except PermissionError:
        return pid
    except (OSError, ValueError):
        return None
    return pid


def reap(cfg: XdpConfig) -> bool:
    """Remove the switch `cfg` if a launcher made it and is gone (SIGKILLed before it could); whether
    it did."""
    if not (OWNERS / cfg.netns).exists() or owner(cfg.netns) is not None:
        return False
    remove(cfg)
    return True


@contextlib.contextmanager
def switch_namespace(cfg: XdpConfig) -> Iterator[None]:
    """The switch's namespace and veth pair, up for the duration; SwitchError if they cannot be made
    (a namespace of that name exists and is not a dead launcher's: another cell runs with the XDP
    backend, or it is not ours)."""
    if problem := xdp_missing():
        raise SwitchError(f'[dataplane] backend = "xdp" cannot run: {problem}')
    if os.path.exists(f"/var/run/netns/{cfg.netns}"):
        if reap(cfg):
            log.warning("switch %s was left by a cell that was killed: removed and made anew", cfg.netns)
        elif (pid := owner(cfg.netns)) is not None:
            raise SwitchError(f"network namespace {cfg.netns!r} is the switch of a running cell (pid {pid})")
        else:
            raise SwitchError(
                f"network namespace {cfg.netns!r} exists and no cell made it "
                f"(`ip netns del {cfg.netns}` if it is not needed, or set [dataplane.xdp] netns)"
            )
    host, sw = f"{cfg.veth}0", f"{cfg.veth}1"
    try:
        _ip("netns", "add", cfg.netns)
        OWNERS.mkdir(exist_ok=True)
        (OWNERS / cfg.netns).write_text(str(os.getpid()))
        _ip("link", "add", host, "type", "veth", "peer", "name", sw, "netns", cfg.netns)
        _ip("addr", "add", f"{cfg.host_addr}/{cfg.prefix}", "dev", host)
        _ip("link", "set", host, "up")
        _ip("-n", cfg.netns, "addr", "add", f"{cfg.switch_addr}/{cfg.prefix}", "dev", sw)
        _ip("-n", cfg.netns, "link", "set", sw, "up")
        _ip("-n", cfg.netns, "link", "set", "lo", "up")
        if cfg.cpu >= 0:  # the pipeline on one CPU, in packet order, as a switch's (RPS)
            rps = f"/sys/class/net/{sw}/queues/rx-0/rps_cpus"
            _ip("netns", "exec", cfg.netns, "sh", "-c", f"echo {1 << cfg.cpu:x} > {rps}")
        yield
    finally:
        remove(cfg)


def enter(netns: str) -> None:
    """The calling thread into the network namespace (for good: sockets and interfaces it opens
    from now on are there)."""
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    fd = os.open(f"/var/run/netns/{netns}", os.O_RDONLY)
    try:
        if libc.setns(fd, CLONE_NEWNET):
            raise SwitchError(f"entering namespace {netns}: {os.strerror(ctypes.get_errno())}")
    finally:
        os.close(fd)


def namespace_thread(netns: str, off_cpus: frozenset[int] = frozenset()) -> ThreadPoolExecutor:
    """One thread that lives inside the namespace: calls there without a new thread each (an XDP
    attach can take 15 ms; the event loop awaits it instead of stopping for it).  off_cpus: CPUs it
    leaves (unless they are all there are), at the normal policy: an attach holds its CPU in the
    kernel for 15-70 ms, which on the robots' core cost them ticks and protective stops (cell chaos
    xdp-detached)."""

    def start() -> None:
        enter(netns)
        elsewhere = set(range(os.cpu_count() or 1)) - off_cpus
        with contextlib.suppress(OSError, AttributeError):  # (the calling thread only; Linux)
            if off_cpus and elsewhere:
                os.sched_setaffinity(0, elsewhere)
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))

    return ThreadPoolExecutor(1, thread_name_prefix=f"netns:{netns}", initializer=start)


def in_namespace(netns: str, fn: Callable[[], T]) -> T:
    """fn() on a thread inside the network namespace (sockets and interfaces it opens stay there)."""
    out: list[T] = []
    err: list[BaseException] = []

    def body() -> None:
        try:
            enter(netns)
            out.append(fn())
        except BaseException as exc:  # carried to the caller's thread
            err.append(exc)

    t = threading.Thread(target=body, name=f"netns:{netns}")
    t.start()
    t.join()
    if err:
        raise err[0]
    return out[0]
