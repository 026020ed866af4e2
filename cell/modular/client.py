"""The modular robot from task scripts and the command line: `await cell.modular.move(...)`."""

from __future__ import annotations

from collections.abc import Sequence

from cell.bus import Bus
from cell.v1 import modular_pb2 as pb


class ModularClient:
    def __init__(self, bus: Bus) -> None:
        self.bus = bus

    async def move(
        self,
        joints: Sequence[float] = (),
        *,
        tool: Sequence[float] = (),
        path: str = "",
        speed: float = 0.0,
        timeout: float = 120.0,
    ) -> pb.ModularMoveReply:
        """A joint goal (rad), a tool position (m) or a named path ("pick-and-place", "circle");
        answered when the motion ends, with the tool's error against its reference.  RemoteError
        "refused" (stopped, busy, a bad goal) or "stopped" (a module was lost on the way)."""
        req = pb.ModularMoveRequest(joints=list(joints), tool=list(tool), path=path, speed=speed)
        return await self.bus.request("modular", "move", req, pb.ModularMoveReply, timeout)

    async def plug(self, module: str, timeout: float = 5.0) -> pb.ModularStatus:
        return await self._module("plug", module, timeout)

    async def unplug(self, module: str, timeout: float = 5.0) -> pb.ModularStatus:
        return await self._module("unplug", module, timeout)

    async def status(self, timeout: float = 5.0) -> pb.ModularStatus:
        return await self.bus.request(
            "modular", "status", pb.ModularStatusRequest(), pb.ModularStatus, timeout
        )

    async def _module(self, method: str, module: str, timeout: float) -> pb.ModularStatus:
        req = pb.ModularModuleRequest(module=module)
        return await self.bus.request("modular", method, req, pb.ModularStatus, timeout)
