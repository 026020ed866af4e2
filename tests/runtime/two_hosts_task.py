"""Task script of tests/runtime/test_two_hosts.py: both robots (one per host) start a long joint motion,
say so, and wait for their arrival; the test kills host b meanwhile.  Prints, last, one JSON line:
per robot, how its `break` was answered and when (CLOCK_MONOTONIC s, shared by the namespaces)."""

from __future__ import annotations

import asyncio
import json
import time

from cell.skills.client import Break, MoveRelJoints, SkillError

SWING = (100.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # deg: over a second of motion


async def arrive(robot) -> list:
    try:
        await robot.cmdexec(Break(), timeout=30.0)
    except SkillError as exc:
        return [exc.code, exc.text, time.monotonic()]
    return ["done", "", time.monotonic()]


async def main(cell) -> None:
    r1, r2 = cell.robot("r1"), cell.robot("r2")
    await asyncio.gather(*(r.cmdexec(MoveRelJoints(SWING, brk=False)) for r in (r1, r2)))
    print("moving", time.monotonic(), flush=True)
    results = await asyncio.gather(arrive(r1), arrive(r2))
    print(json.dumps({"r1": results[0], "r2": results[1]}), flush=True)
