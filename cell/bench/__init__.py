"""Benchmarks behind `cell bench ...`: each measures a hot path next to a baseline in the same run.

Every module here is imported to list the benches (registry.discover), so a bench imports what only
its run needs (another bench's parts, the cell's engines, what builds C) inside the functions that
run it: `cell bench --help` then loads about a second's worth, not every bench's."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator


def pin(core: int) -> None:
    """Keep this process on one core (where the machine has it), so each side of a benchmark owns one."""
    if hasattr(os, "sched_setaffinity") and core < (os.cpu_count() or 1):
        os.sched_setaffinity(0, {core})


@contextlib.contextmanager
def pinned(core: int) -> Iterator[None]:
    """pin(core) for the block, then the CPUs this process had (a benchmark run inside another
    program, a test say, must not leave it, and every process it starts later, on one core)."""
    before = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    pin(core)
    try:
        yield
    finally:
        if before is not None:
            os.sched_setaffinity(0, before)
