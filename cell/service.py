"""What a service is: a named coroutine, run(ctx), and the context the runtime hands it."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from cell.bus import Bus
from cell.config import CellConfig


@dataclass(frozen=True)
class ServiceSpec:
    name: str
    run: Callable[[ServiceContext], Awaitable[None]]
    description: str = ""
    # connect ctx.bus before run() (False only for the forwarder, which the bus needs first)
    needs_bus: bool = True
    # the service is serving as soon as run() starts; False: run() calls ctx.ready() itself
    ready_on_start: bool = True


class ServiceContext:
    """Handed to a service's run(): its config, bus node, logger and the counters its heartbeat reports."""

    def __init__(
        self, name: str, config: CellConfig, bus: Bus | None, on_ready: Callable[[], None] | None = None
    ) -> None:
        self.name = name
        self.config = config
        self._bus = bus
        self.log = logging.getLogger(f"cell.service.{name}")
        self.counters: dict[str, float] = {}
        self._ready = asyncio.Event()
        self._on_ready = on_ready

    @property
    def bus(self) -> Bus:
        if self._bus is None:
            raise RuntimeError(f"service {self.name!r} runs without a bus node (needs_bus=False)")
        return self._bus

    @property
    def has_bus(self) -> bool:
        return self._bus is not None

    def ready(self) -> None:
        """Say the service is serving (its sockets are bound); its heartbeat turns RUNNING."""
        if not self._ready.is_set():
            self._ready.set()
            if self._on_ready is not None:
                self._on_ready()

    @property
    def is_ready(self) -> bool:
        return self._ready.is_set()

    async def wait_ready(self) -> None:
        await self._ready.wait()
