"""The cell's services, one module per service (installed as cell.services).

Each module defines SERVICE, a cell.service.ServiceSpec, and can run alone with
`cell service NAME`.  Users add their own with [services.plugins] in the config.
"""

from __future__ import annotations

import importlib
import inspect

from cell.config import CellConfig, ConfigError
from cell.service import ServiceSpec

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
