"""Two robots pick and place at the same time (run: `cell run examples/pick_and_place.py --up`).

Each robot goes over its pick point, descends along its tool axis, grips
(vacuum on), lifts, carries the part to its place point, sets it down
(vacuum off) and lifts again.  The two sequences are coroutines run together.
"""

from __future__ import annotations

import asyncio

from cell.skills.client import DisableAir, EnableAir, MoveRelWorld, MoveToolZ, SetSpeed

APPROACH = 60.0  # mm above the part, along the tool axis (the tool points down: +z of the tool is down)


async def pick_and_place(robot, pick: tuple[float, float], place: tuple[float, float]) -> list:
    acks = []
    acks += await robot.cmdexec(SetSpeed(80), MoveRelWorld(x=pick[0], y=pick[1]))
    acks += await robot.cmdexec(MoveToolZ(APPROACH), EnableAir(), MoveToolZ(-APPROACH))
    acks += await robot.cmdexec(SetSpeed(80), MoveRelWorld(x=place[0] - pick[0], y=place[1] - pick[1]))
    acks += await robot.cmdexec(MoveToolZ(APPROACH), DisableAir(), MoveToolZ(-APPROACH))
    return acks


async def main(cell) -> None:
    async with asyncio.TaskGroup() as tg:
        a = tg.create_task(pick_and_place(cell.robot("r1"), pick=(80.0, 0.0), place=(0.0, 80.0)))
        b = tg.create_task(pick_and_place(cell.robot("r2"), pick=(-80.0, 0.0), place=(0.0, -80.0)))
    for name, acks in (("r1", a.result()), ("r2", b.result())):
        t0, t1 = acks[0].t_start, acks[-1].t_end
        print(f"{name}: {len(acks)} messages acknowledged, {t1 - t0:.2f} s, ends at {acks[-1].pose}")
