"""An emergency stop from a task script (run: `cell run examples/estop.py --up`).

r1 starts a long move; once it is under way the script e-stops it over the
Responsive Link (the event link, not the bus), waits until it stands, shows
that a motion is refused meanwhile, releases it and sends it home.
"""

from __future__ import annotations

import asyncio

from cell.skills.client import MoveRelWorld, SkillError
from cell.v1 import robot_pb2


async def main(cell) -> None:
    r1 = cell.robot("r1")
    under_way = lambda t: max(map(abs, t.qd)) > 0.1  # noqa: E731
    moving = await cell.expect("truth/r1", robot_pb2.RobotTruth, under_way, timeout=10.0)
    move = asyncio.create_task(r1.cmdexec(MoveRelWorld(x=-250.0)))  # its break waits for the arrival
    await moving  # under way
    took = await cell.estop("r1")
    print(f"r1 e-stopped: standing still {took['r1']:.0f} ms after the order")
    try:
        await move
        raise RuntimeError("the interrupted move was answered done")
    except SkillError as exc:
        print(f"the interrupted move: {exc.code}")
    try:
        await r1.cmdexec(MoveRelWorld(x=10.0))
        raise RuntimeError("a stopped robot took a motion")
    except SkillError as exc:
        print(f"a motion while stopped: {exc.code} ({exc.text})")
    await cell.resume("r1")
    acks = await r1.cmdexec(MoveRelWorld(x=50.0))
    print(f"released; moved on to {acks[-1].pose[:3]}")
