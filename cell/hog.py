"""A host's other work, as a load: one busy process per CPU at the normal policy and nice 0 (a
compiler, a batch job), for `cell chaos --hog`, `cell bench snp --hog` and the tests that
show the packet path keeps its ticks under it.  Each process spins until told to stop, and stops by
itself after `max_s` whatever happens to its parent."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator

SPIN = """
import os, sys, time
end = time.monotonic() + float(sys.argv[1])
os.sched_setaffinity(0, {int(sys.argv[2])})
while time.monotonic() < end:
    for _ in range(100_000):
        pass
"""


@contextlib.contextmanager
def hog(max_s: float = 3600.0, cpus: list[int] | None = None) -> Iterator[list[subprocess.Popen[bytes]]]:
    """One spinning process on each of `cpus` (None: every CPU) until the block ends (or max_s)."""
    cpus = sorted(os.sched_getaffinity(0)) if cpus is None else cpus
    procs = []
    try:
        for cpu in cpus:  # (one at a time: those started before a failure are killed below)
            procs.append(  # noqa: PERF401
                subprocess.Popen(
                    [sys.executable, "-c", SPIN, str(max_s), str(cpu)],
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.DEVNULL,
                    preexec_fn=_normal,  # (not the caller's real-time policy, if it has one)
                )
            )
        yield procs
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()


def _normal() -> None:
    with contextlib.suppress(OSError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        os.setpriority(os.PRIO_PROCESS, 0, 0)
