"""Benchmarks behind `cell bench ...`: each measures a hot path next to a baseline in the same run."""

from __future__ import annotations

import os


def pin(core: int) -> None:
    """Keep this process on one core (where the machine has it), so each side of a benchmark owns one."""
    if hasattr(os, "sched_setaffinity") and core < (os.cpu_count() or 1):
        os.sched_setaffinity(0, {core})
