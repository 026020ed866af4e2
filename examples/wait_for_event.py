"""Wait for a bus event while a robot moves (run: `cell run examples/wait_for_event.py --up`).

r1 moves away; meanwhile the script waits for r2's vacuum to come on (an
event on the bus, here caused by r2 itself a moment later); when it has, r1
comes back.  Coroutines composed with a TaskGroup, as pyadept's scripts do.
"""

from __future__ import annotations

import asyncio

from cell.skills.client import DisableAir, EnableAir, MoveRelWorld
from cell.v1 import skills_pb2


async def main(cell) -> None:
    r1, r2 = cell.robot("r1"), cell.robot("r2")
    # listen first (live on return), then move r1 away and, meanwhile, have r2 switch its vacuum on
    air = await cell.expect("skills/r2/air", skills_pb2.AirState, lambda s: s.on, timeout=30.0)
    async with asyncio.TaskGroup() as tg:
        away = tg.create_task(r1.cmdexec(MoveRelWorld(x=100.0)))
        tg.create_task(r2.cmdexec(EnableAir()))
        event = await air
    print(f"r1 moved away ({away.result()[-1].pose[:3]}); r2's vacuum came on at {event.t_ns / 1e9:.3f} s")
    await asyncio.gather(r1.cmdexec(MoveRelWorld(x=-100.0)), r2.cmdexec(DisableAir()))
