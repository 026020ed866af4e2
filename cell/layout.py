"""How a cell's services map onto OS processes, and how the OS schedules each (`[services] layout`).

- "groups" (the default): one process per [[services.groups]] entry that has a
  service to run, and one more, "main", for every service no group names.  The
  default config gives the packet path (robots, dataplane) processes of their
  own, pinned and at a real-time priority, so that no bus traffic, planning,
  recording or rendering ever stands between a robot and its next tick.
- "single": everything in the launcher's process and event loop (debugging).
- "each": one process per service (a service in a group keeps the group's scheduling).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from cell.config import MAIN_GROUP, CellConfig, ConfigError, ProcessGroup


@dataclass(frozen=True)
class Process:
    """One OS process of the cell: its name, its services (in `run` order) and its scheduling."""

    name: str
    services: list[str]
    cpus: list[int]
    rt_priority: int
    nice: int
    bus: tuple[str, str] | None = None  # (pub, sub) in place of [bus]'s, if its group says so

    @classmethod
    def of(cls, name: str, services: list[str], group: ProcessGroup | None) -> Process:
        if group is None:
            return cls(name, services, [], 0, 0)
        bus = (group.bus_pub, group.bus_sub) if group.bus_pub else None
        # a real-time group's priority is for its native loops (the robots' tick, the data plane's
        # packet path), which hand the rest of their process to the normal policy: a process of the
        # group without one (the Responsive Link's hub alone, in the "each" layout) runs as the rest
        # would, at the group's nice and CPUs, never all its Python at the tick's priority
        rt = group.rt_priority if NATIVE_LOOPS & set(services) else 0
        return cls(name, services, list(group.cpus), rt, group.nice, bus)

    def config_for(self, config: CellConfig) -> CellConfig:
        """The config this process's services run with (its bus endpoints, if they differ)."""
        if self.bus is None:
            return config
        return replace(config, bus=replace(config.bus, pub=self.bus[0], sub=self.bus[1]))


NATIVE_LOOPS = {"robots", "dataplane"}  # the services whose per-tick loop runs in C at real-time priority


def _group_of(config: CellConfig) -> dict[str, ProcessGroup]:
    return {name: g for g in config.services.groups for name in g.services}


def processes(config: CellConfig) -> list[Process]:
    """The processes `cell up` starts for this config's layout, "main" first."""
    s = config.services
    group_of = _group_of(config)
    if s.layout == "single":
        return [Process.of(MAIN_GROUP, list(s.run), None)]
    if s.layout == "each":
        return [Process.of(name, [name], group_of.get(name)) for name in s.run]
    rest = [name for name in s.run if name not in group_of]
    out = [Process.of(MAIN_GROUP, rest, None)] if rest else []
    for g in s.groups:
        names = [name for name in s.run if name in g.services]
        if names:
            out.append(Process.of(g.name, names, g))
    return out


def process_named(config: CellConfig, name: str) -> Process:
    """The process `name` of the "groups" layout (`cell service --group NAME`); ConfigError if none."""
    s = config.services
    as_groups = replace(config, services=replace(s, layout="groups"))
    for p in processes(as_groups):
        if p.name == name:
            return p
    known = [MAIN_GROUP, *(g.name for g in s.groups)]
    raise ConfigError(
        config.source,
        "services.groups",
        f"no process group {name!r} with services to run ({', '.join(known)})",
    )


def process_for(config: CellConfig, names: list[str]) -> Process:
    """The process `cell service NAME...` runs: the scheduling of the group holding all of the
    names, if one does (so `cell service robots` is placed as `cell up` would place it)."""
    group_of = _group_of(config)
    first = group_of.get(names[0]) if names else None
    group = first if all(group_of.get(n) is first for n in names) else None
    label = names[0] if len(names) == 1 else (group.name if group is not None else MAIN_GROUP)
    return Process.of(label, list(names), group)
