"""What a service is: a named coroutine, run(ctx), and the context the runtime hands it; and the
registry of services: the built-ins (one module each in services/, installed as cell.services) and
users' plugins ([services.plugins] name = "module:attr").  A built-in is imported only when run."""

from __future__ import annotations

import asyncio
import importlib
import inspect
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from cell.bus import Bus
from cell.config import CellConfig, ConfigError


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


# name -> module; imported only when the service is run
BUILTIN: dict[str, str] = {
    "bus": "cell.services.bus",
    "robots": "cell.services.robots",
    "dataplane": "cell.services.dataplane",
    "controller": "cell.services.controller",
    "skills": "cell.services.skills",
    "snp": "cell.services.snp",
    "recorder": "cell.services.recorder",
    "rlink": "cell.services.rlink",
    "vision": "cell.services.vision",
    "modular": "cell.services.modular",
}


def load(name: str, config: CellConfig) -> ServiceSpec:
    """The spec of a built-in or plugin service; ConfigError if the name or its entry point is bad."""
    key = f"services.plugins.{name}"
    if name in config.services.plugins:
        entry = config.services.plugins[name]
        module_name, _, attr = entry.partition(":")
        try:
            obj = getattr(importlib.import_module(module_name), attr)
        except (ImportError, AttributeError) as exc:
            raise ConfigError(config.source, key, f"cannot load {entry!r}: {exc}") from None
        if isinstance(obj, ServiceSpec):
            return (
                obj
                if obj.name == name
                else ServiceSpec(name, obj.run, obj.description, obj.needs_bus, obj.ready_on_start)
            )
        if inspect.iscoroutinefunction(obj):
            return ServiceSpec(name, obj, (obj.__doc__ or "").strip().split("\n")[0])
        raise ConfigError(config.source, key, f"{entry!r} is neither a ServiceSpec nor an async function")
    if name in BUILTIN:
        return importlib.import_module(BUILTIN[name]).SERVICE
    known = sorted(BUILTIN) + sorted(config.services.plugins)
    raise ConfigError(config.source, "services.run", f"unknown service {name!r} (known: {', '.join(known)})")


def load_all(config: CellConfig, names: list[str] | None = None) -> list[ServiceSpec]:
    return [load(n, config) for n in (config.services.run if names is None else names)]


def check_all(config: CellConfig, names: list[str] | None = None) -> None:
    """ConfigError unless every name is a built-in service or a loadable plugin; the built-ins are
    not imported (a launcher that runs none of them starts its children sooner)."""
    for name in config.services.run if names is None else names:
        if name not in BUILTIN or name in config.services.plugins:
            load(name, config)
