"""The master control node: `cell run SCRIPT.py` runs a task script's `async def main(cell)`.

The script gets a `Cell`: its robots by name as connected `RobotClient`s, the
bus, a request helper matched by id with a timeout, a way to wait for a bus
event, and the controller for what the skill protocol cannot say
(synchronised starts).  Scripts compose coroutines with asyncio.TaskGroup or
gather, as pyadept's do.  The run is announced on the bus (run/events), and
every robot request is traced there (run/<robot>/request).
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import inspect
import logging
import os
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from google.protobuf.message import Message

from cell.bus import Bus
from cell.config import CellConfig
from cell.launcher import child_cell
from cell.modular.client import ModularClient
from cell.rlink.client import EventClient
from cell.skills.client import RobotClient
from cell.trajectory.cartesian import solve_where_it_stands
from cell.trajectory.model import Trajectory
from cell.trajectory.wire import to_message
from cell.v1 import controller_pb2, skills_pb2
from cell.vision.client import VisionClient

log = logging.getLogger("cell.run")
M = TypeVar("M", bound=Message)


class Cell:
    """What a task script's main() is given."""

    def __init__(
        self, config: CellConfig, bus: Bus, robots: dict[str, RobotClient], link: EventClient | None = None
    ) -> None:
        self.config, self.bus, self.robots, self.link = config, bus, robots, link
        self.vision = VisionClient(bus)  # the camera service: `await cell.vision.request()`
        self.modular = ModularClient(bus)  # the modular robot: `await cell.modular.move(...)`

    def _link(self) -> EventClient:
        if self.link is None:
            raise RuntimeError("this Cell has no Responsive Link client")
        return self.link

    async def estop(self, *robots: str, timeout: float = 5.0) -> dict[str, float]:
        """Emergency stop over the Responsive Link (every robot if none is named); returns once each
        stands still, with the ms it took.  Motions are answered `stopped` until resume()."""
        took = await self._link().estop(list(robots) or None, timeout=timeout)
        return self._named(took)

    async def resume(self, *robots: str, timeout: float = 5.0) -> dict[str, float]:
        """Release robots stopped over the Responsive Link (every robot if none is named)."""
        return self._named(await self._link().resume(list(robots) or None, timeout=timeout))

    def _named(self, by_id: dict[int, float]) -> dict[str, float]:
        names = {r.id: r.name for r in self.config.robots}
        return {names.get(rid, str(rid)): ms for rid, ms in by_id.items()}

    def robot(self, name: str) -> RobotClient:
        try:
            return self.robots[name]
        except KeyError:
            if not self.robots:
                why = "this cell runs no skill servers (service `skills`)"
                raise KeyError(f"no robot {name!r}: {why}") from None
            raise KeyError(f"no robot {name!r} in this cell (robots: {', '.join(self.robots)})") from None

    async def request(
        self, service: str, method: str, msg: Message, reply_type: type[M], timeout: float = 5.0
    ) -> M:
        """A request over the bus, its reply matched by id; BusTimeout after `timeout` s."""
        return await self.bus.request(service, method, msg, reply_type, timeout)

    async def expect(
        self,
        topic: str,
        message_type: type[Message],
        predicate: Callable[[Any], bool] = lambda _m: True,
        timeout: float | None = None,
    ) -> asyncio.Task:
        """A task that ends with the next message on topics starting with `topic` satisfying
        predicate; the subscription is live when this returns, so nothing sent after is missed."""
        sub = await self.bus.subscribe(topic)

        async def wait() -> Any:
            try:
                async with asyncio.timeout(timeout):
                    async for msg in sub.messages(message_type):
                        if predicate(msg):
                            return msg
            finally:
                sub.close()

        return asyncio.create_task(wait())

    async def wait_event(
        self,
        topic: str,
        message_type: type[Message],
        predicate: Callable[[Any], bool] = lambda _m: True,
        timeout: float | None = None,
    ) -> Any:
        """The next such message (see expect)."""
        return await (await self.expect(topic, message_type, predicate, timeout))

    async def move_together(
        self, goals_deg: dict[str, list[float]], speed: float = 100.0
    ) -> tuple[float, float]:
        """Robots to joint goals (deg) with one shared start time (the skill protocol has no way to
        say this); (start, end) on the data-plane clock, s."""
        req = controller_pb2.MoveTogetherRequest(
            moves=[
                controller_pb2.MoveRequest(robot=name, values=np.radians(q).tolist(), speed=speed)
                for name, q in goals_deg.items()
            ]
        )
        reply = await self.request("controller", "move_together", req, controller_pb2.MoveReply, 120.0)
        return reply.t_start_ns / 1e9, reply.t_end_ns / 1e9

    async def follow(
        self, trajectories: dict[str, Trajectory], speed: float = 50.0, replace: bool = False
    ) -> controller_pb2.MoveReply:
        """Trajectories planned elsewhere (cell.trajectory.model.Trajectory, columns in each robot's
        joint order), one per robot, their time 0 at one data-plane time (docs/trajectories.md);
        the reply when all have ended, its t0_ns when their time 0 was.  replace: a robot under way
        is switched onto its trajectory on the fly (one robot)."""
        req = controller_pb2.FollowRequest(
            speed=speed,
            trajectories=[
                to_message(robot, tr.t, tr.q, tr.qd, tr.qdd, name=tr.name)
                for robot, tr in trajectories.items()
            ],
            replace=replace,
        )
        timeout = max(t.duration for t in trajectories.values()) + 120.0
        return await self.request(
            "controller", "follow", req, controller_pb2.MoveReply, timeout
        )  # (MoveReply)

    async def cartesian(self, robot: str, poses) -> Trajectory:
        """A Cartesian path (cell.trajectory.cartesian.Poses: tool positions in m in the robot's base
        frame, optional rotations, times or a maximum tool speed) as the robot's joint trajectory,
        solved by IK from where it stands now; TrajectoryError naming a waypoint out of reach.
        Follow it with follow({robot: ...})."""
        return await solve_where_it_stands(self.bus, self.config, robot, poses)

    async def name_trajectories(
        self, name: str, trajectories: dict[str, Trajectory]
    ) -> controller_pb2.NameReply:
        """Give the cell trajectories under a name (checked now; a name given again is replaced), for
        the skill servers' follow:<name> (`Follow(name)` on a robot client) and follow_named()."""
        req = controller_pb2.NameRequest(
            name=name,
            trajectories=[
                to_message(r, tr.t, tr.q, tr.qd, tr.qdd, name=tr.name) for r, tr in trajectories.items()
            ],
        )
        return await self.request("controller", "name", req, controller_pb2.NameReply, 30.0)

    async def follow_named(self, name: str, *robots: str, speed: float = 50.0) -> controller_pb2.MoveReply:
        """Run the trajectories named so (of these robots, or all) together; the reply when all have ended."""
        req = controller_pb2.FollowRequest(name=name, robots=list(robots), speed=speed)
        return await self.request("controller", "follow", req, controller_pb2.MoveReply, 3600.0)

    async def prepare_alternates(
        self, robot: str, goals_deg: dict[str, list[float]], speed: float = 100.0, every: int = 1
    ) -> int:
        """For the robot's running motion (started with start_only): branches to other joint goals
        (deg), prepared from its TPs ahead and loaded (Sec. 6.1 of the NSDI'22 paper); the TPs
        loaded.  take_alternate(), or an event on alternate/<robot>, switches onto one."""
        req = controller_pb2.AlternatesRequest(
            robot=robot,
            alternates=[
                controller_pb2.Alternate(name=n, values=np.radians(q).tolist()) for n, q in goals_deg.items()
            ],
            speed=speed,
            every=every,
        )
        reply = await self.request(
            "controller", "prepare_alternates", req, controller_pb2.AlternatesReply, 60.0
        )
        return int(reply.tps_loaded)

    async def take_alternate(self, robot: str, name: str) -> tuple[float, float]:
        """Onto a prepared alternate at the next TP in reach (no planning); (start, end) when it has
        ended, on the data-plane clock, s."""
        req = controller_pb2.TakeAlternate(robot=robot, name=name)
        reply = await self.request("controller", "take_alternate", req, controller_pb2.MoveReply, 120.0)
        return reply.t_start_ns / 1e9, reply.t_end_ns / 1e9

    def arm_alternate(self, robot: str, name: str) -> None:
        """The same as an event anyone on the bus may send (topic alternate/<robot>): no reply."""
        self.bus.publish(f"alternate/{robot}", controller_pb2.TakeAlternate(robot=robot, name=name))

    async def loop(
        self, robot: str, waypoints_deg: list[list[float]], laps: int = 0, speed: float = 100.0
    ) -> int:
        """A repetitive task as a TPStepper loop: from where the robot stands through the waypoints
        (deg) and back, loaded once, run `laps` times; returns the laps run.  With laps=0 it runs
        until end_loop() (run this in a task)."""
        values = np.radians(np.asarray(waypoints_deg, np.float64)).ravel().tolist()
        req = controller_pb2.LoopRequest(robot=robot, values=values, laps=laps, speed=speed)
        reply = await self.request("controller", "loop", req, controller_pb2.LoopReply, 3600.0)
        return int(reply.laps)

    async def end_loop(self, robot: str) -> int:
        """End the robot's loop at the end of the lap in reach; the laps it runs."""
        req = controller_pb2.RobotRequest(robot=robot)
        reply = await self.request("controller", "end_loop", req, controller_pb2.LoopReply, 10.0)
        return int(reply.laps)


def load_main(path: Path) -> Callable[[Cell], Any]:
    """The script's `async def main(cell)`; ValueError saying what is wrong."""
    spec = importlib.util.spec_from_file_location(f"cell_script_{path.stem}", path)
    if spec is None or spec.loader is None:
        raise ValueError(f"{path}: not a Python file")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    main = getattr(module, "main", None)
    if main is None or not inspect.iscoroutinefunction(main):
        raise ValueError(f"{path}: defines no `async def main(cell)`")
    return main


async def run_script(
    path: Path, config: CellConfig, config_path: Path | None = None, up: bool = False
) -> int:
    """Run the script against the cell (started first with up); 0 when main() returned."""
    try:
        main = load_main(path)
    except Exception as exc:  # a script that does not even load
        print(f"cell run: {exc}", file=sys.stderr)
        return 2
    async with contextlib.AsyncExitStack() as stack:
        if up:
            await stack.enter_async_context(child_cell(config_path, config))
        bus = await stack.enter_async_context(Bus.connect(config.bus, f"run-{os.getpid()}"))
        robots: dict[str, RobotClient] = {}
        host = config.skills.host
        for r in config.robots if config.runs("skills") else ():  # (no skill servers: no robot clients)
            client = RobotClient(r.name, host, r.skill_port, bus)
            try:
                await client.connect(timeout=10.0)
            except TimeoutError:
                print(
                    f"cell run: no skill server for {r.name} at {host}:{r.skill_port} "
                    "(is the `skills` service running? `cell run --up` starts a cell)",
                    file=sys.stderr,
                )
                return 1
            stack.push_async_callback(client.close)
            robots[r.name] = client
        link = await stack.enter_async_context(EventClient(config))
        cell = Cell(config, bus, robots, link)
        event = skills_pb2.RunEvent(script=str(path), state="started", t_ns=time.monotonic_ns())
        bus.publish("run/events", event)
        t0 = time.monotonic()
        try:
            await main(cell)
        except Exception as exc:
            traceback.print_exc()
            bus.publish(
                "run/events",
                skills_pb2.RunEvent(
                    script=str(path), state="failed", t_ns=time.monotonic_ns(), text=repr(exc)
                ),
            )
            return 1
        bus.publish(
            "run/events", skills_pb2.RunEvent(script=str(path), state="done", t_ns=time.monotonic_ns())
        )
        log.info("%s done in %.2f s", path, time.monotonic() - t0)
    return 0
