"""The cell's status: the launcher keeps every service's last heartbeat and answers `cell.status`.

`cell status` is then one request away, instead of waiting a heartbeat period
to hear every service; services another host runs show up as soon as their
heartbeats arrive.
"""

from __future__ import annotations

import os
import socket
import time
from enum import StrEnum

from cell import rtbudget
from cell.bus import Bus, identity
from cell.config import CellConfig
from cell.v1 import health_pb2

POLL_TOPIC = "health-poll"  # supervisors answer a message here with their heartbeats at once
STALE_AFTER = 2.5  # heartbeat periods without news before a service is "stale"


class Health(StrEnum):
    """A service's health as `cell.status` answers it (ServiceStatus.health: these strings on the
    wire, and in `cell status --json`): its heartbeat's state, or what the launcher makes of its
    heartbeats' absence; health.proto's Health is its source for other languages
    (tests/bus/test_proto.py holds the two equal)."""

    OK = "ok"
    STARTING = "starting"
    BACKOFF = "backoff"  # failed, to be restarted
    FAILED = "failed"  # failed, not to be restarted
    STOPPED = "stopped"
    STALE = "stale"  # heartbeats overdue
    MISSING = "missing"  # never heard
    UNKNOWN = "unknown"  # a state this launcher does not know (a newer service's)


_HEALTH = {
    health_pb2.SERVICE_STATE_STARTING: Health.STARTING,
    health_pb2.SERVICE_STATE_RUNNING: Health.OK,
    health_pb2.SERVICE_STATE_BACKOFF: Health.BACKOFF,
    health_pb2.SERVICE_STATE_FAILED: Health.FAILED,
    health_pb2.SERVICE_STATE_STOPPED: Health.STOPPED,
}


def status_names(config: CellConfig, everywhere: bool = False) -> list[str]:
    """The names `cell status` gives this host's services (every host's with `everywhere`): in a
    cell of several hosts a service is `name@host`, since two hosts may both run `robots`."""
    if not config.hosts:
        return list(config.services.run)
    hosts = config.hosts.items() if everywhere else [(config.cell.host, config.hosts[config.cell.host])]
    return [f"{s}@{h}" for h, c in hosts for s in c.run]


def host_name(config: CellConfig) -> str:
    """This host in heartbeats: its name among [hosts], else the machine's."""
    return config.cell.host or socket.gethostname()


class StatusRegistry:
    """Every service's last heartbeat, by its status name, with every expected one listed."""

    def __init__(
        self,
        cell: str,
        mode: str,
        expected: list[str],
        *,
        host: str = "",
        qualify: bool = False,
        config_source: str = "",
        dataplane: str = "",
    ):
        self.cell = cell
        self.config_source = config_source
        self.dataplane = dataplane  # its backend and why, as the launcher's config chose it
        self.mode = mode
        self.expected = list(expected)
        self.host = host
        self.qualify = qualify  # key services by name@host (a cell of several hosts)
        self.started = time.monotonic()
        self._last: dict[str, tuple[health_pb2.Heartbeat, float]] = {}
        self._process_restarts: dict[str, tuple[int, str]] = {}  # process -> (restarts, why)
        self._bus: Bus | None = None
        self._dead_pid: dict[str, int] = {}  # service -> the pid of its process that died
        self._carried: dict[str, int] = {}  # service -> restarts counted by processes that died since

    def process_restarted(self, process: str, why: str) -> None:
        """A process the launcher runs died and was started again: its services' restarts count it
        (their new supervisor starts counting from 0)."""
        n, _ = self._process_restarts.get(process, (0, ""))
        self._process_restarts[process] = (n + 1, why)
        for name, (hb, _) in self._last.items():
            if hb.process != process or not self._mine(hb):
                continue
            if self._dead_pid.get(name) != hb.pid:
                self._dead_pid[name] = hb.pid  # down until a heartbeat from its new process says otherwise
                self._carried[name] = self._carried.get(name, 0) + hb.restarts  # its in-process restarts
            if self._bus is not None:  # its supervisor died with it: say so in its stead, now
                kind = health_pb2.ServiceEvent.KIND_FAILED
                ev = health_pb2.ServiceEvent(service=hb.service, kind=kind, text=why, restarts=hb.restarts)
                self._bus.publish(f"events/service/{hb.service}", ev)  # (a topic has no '@')

    def _mine(self, hb: health_pb2.Heartbeat) -> bool:
        """A heartbeat of a process this launcher runs (process names repeat across hosts)."""
        return not self.qualify or hb.host == self.host

    @classmethod
    def of(cls, config: CellConfig) -> StatusRegistry:
        return cls(
            config.cell.name,
            config.services.layout,
            status_names(config, everywhere=True),
            host=host_name(config),
            qualify=bool(config.hosts),
            config_source=config.source,
            dataplane="{} ({})".format(*config.dataplane.chosen()) if config.runs("dataplane") else "",
        )

    def observe(self, hb: health_pb2.Heartbeat, at: float | None = None) -> None:
        key = f"{hb.service}@{hb.host}" if self.qualify else hb.service
        self._last[key] = (hb, time.monotonic() if at is None else at)

    def status(self, _request: object = None) -> health_pb2.CellStatus:
        now = time.monotonic()
        out = health_pb2.CellStatus(
            cell=self.cell, mode=self.mode, uptime_s=now - self.started, config=self.config_source,
            launcher_pid=os.getpid(),
            member=identity.member_token(), dataplane=self.dataplane,
        )  # fmt: skip
        names = self.expected + sorted(set(self._last) - set(self.expected))
        for name in names:
            entry = out.services.add(name=name)
            if name not in self._last:
                entry.health = Health.MISSING
                continue
            hb, at = self._last[name]
            entry.last.CopyFrom(hb)
            if hb.process in self._process_restarts and self._mine(hb):
                n, why = self._process_restarts[hb.process]
                entry.last.restarts += n
                entry.last.last_error = entry.last.last_error or why
            ghost = self._dead_pid.get(name) == hb.pid
            # restarts counted by processes that died (a ghost's own count is in it already)
            entry.last.restarts += self._carried.get(name, 0) - (hb.restarts if ghost else 0)
            entry.heartbeat_age_s = now - at
            stale = entry.heartbeat_age_s > STALE_AFTER * max(hb.interval_s, 0.1)
            alive = hb.state not in (health_pb2.SERVICE_STATE_FAILED, health_pb2.SERVICE_STATE_STOPPED)
            entry.health = Health.STALE if stale and alive else _HEALTH.get(hb.state, Health.UNKNOWN)
            if ghost:  # its process died: its last heartbeat is a ghost's
                entry.health = Health.BACKOFF
                entry.last.state = health_pb2.SERVICE_STATE_BACKOFF
        return out

    async def run(self, bus: Bus) -> None:
        """Serve `cell.status` and keep up with heartbeats until cancelled."""
        health = await bus.subscribe("health/")
        await bus.serve("cell", {"status": (health_pb2.StatusRequest, self.status)})
        self._bus = bus
        bus.publish(POLL_TOPIC, health_pb2.StatusRequest())  # no waiting a whole period to hear everyone
        while True:
            for beat in await health.recv_messages(health_pb2.Heartbeat):
                self.observe(beat)


def _fmt_count(v: float) -> str:
    if v == int(v):
        return f"{int(v)}"
    return f"{v:.3g}"


def format_status(st: health_pb2.CellStatus, counters: bool = True) -> str:
    """A table for people: one row per service, counters below it."""
    lines = [f"cell {st.cell!r} (layout {st.mode}), up {st.uptime_s:.1f} s"]
    if st.dataplane:
        lines.append(f"data plane: {st.dataplane}")
    head = (
        "SERVICE",
        "HEALTH",
        "HOST",
        "PID",
        "PROCESS",
        "SCHED",
        "UPTIME",
        "RESTARTS",
        "HEARTBEAT",
        "LAST ERROR",
    )
    rows = [head]
    for s in st.services:
        if s.health == Health.MISSING:
            rows.append((s.name, Health.MISSING, "-", "-", "-", "-", "-", "-", "never", ""))
            continue
        hb = s.last
        rows.append(
            (
                s.name,
                s.health,
                hb.host,
                str(hb.pid),
                hb.process or "-",
                hb.sched or "-",
                f"{hb.uptime_s:.1f} s",
                str(hb.restarts),
                f"{s.heartbeat_age_s:.1f} s ago",
                hb.last_error[:60],
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines += ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows]
    lines += format_robots(st)
    if held := rt_holds(st):
        lines.append(held)
    if spent := rt_budget_spent(st):
        lines.append(spent)
    if counters:
        for s in st.services:
            if s.last.counters:
                items = sorted(
                    (k, v) for k, v in s.last.counters.items() if not _link_counter(k) and not _robot_state(k)
                )
                lines.append(f"  {s.name}: " + ", ".join(f"{k}={_fmt_count(v)}" for k, v in items))
        lines += format_links(st)
    return "\n".join(lines)


RT_DOC = "docs/running.md#rt-throttling"


def rt_holds(st: health_pb2.CellStatus) -> str | None:
    """The cell's real-time processes held runnable but not run (sched.Held), in one line; "" if they
    never were, None if no process runs at a real-time priority (none watched).  Such a hold is the
    kernel's RT throttling when every real-time thread of its CPU was held at once, and a thread of
    a higher priority on its CPU when one alone was: the processes' counters cannot tell which, the
    INFO log of cell.sched can (each hold's thread, CPU and policy)."""
    held: dict[str, tuple[float, float, float]] = {}
    for s in st.services:
        c = s.last.counters
        if "process.rt.held" in c:
            held[s.last.process or s.name] = (
                c["process.rt.held"],
                c.get("process.rt.held_ms", 0.0),
                c.get("process.rt.held_max_ms", 0.0),
            )
    if not held:
        return None
    hit = {p: v for p, v in held.items() if v[0]}
    if not hit:
        return ""
    each = "; ".join(f"{p} {n:.0f}x, {ms:.0f} ms" for p, (n, ms, _) in sorted(hit.items()))
    longest = max(m for _, _, m in hit.values())
    return (
        f"RT holds: real-time processes were held runnable but not run ({each}; longest {longest:.0f} ms): "
        f"the kernel's RT throttling or a higher priority on their CPU; see {RT_DOC}"
    )


def rt_budget_spent(st: health_pb2.CellStatus) -> str:
    """The processes whose Python ran out of its real-time budget (cell.rtbudget), in one line; ""
    if none did."""
    spent: dict[str, tuple[float, float]] = {}
    for s in st.services:
        c = s.last.counters
        if c.get("process.rt.budget_spent", 0.0):
            spent[s.last.process or s.name] = (
                c["process.rt.budget_spent"],
                c.get("process.rt.budget_normal_ms", 0.0),
            )
    if not spent:
        return ""
    each = "; ".join(f"{p} {n:.0f}x, {ms:.0f} ms" for p, (n, ms) in sorted(spent.items()))
    return (
        f"RT budget: a real-time process's Python had more work than {rtbudget.SHARE:.0%} of its CPU and ran "
        f"at the normal policy meanwhile ({each}), not to stop its CPU's native loops; see {RT_DOC}"
    )


# what each code of robot.<name>.state means (cell.robot.node.robot_states)
ROBOT_STATES = (
    "standing",
    "moving",
    "protective stop (no commands for its watchdog's windows)",
    "e-stopped (cell resume releases it)",
    "held by its UR state (powered off, braked or safety-stopped)",
    "under a URScript program",
    "mute (a fault injected: robot/<name>.silence)",
)


def _robot_state(key: str) -> bool:
    return key.startswith("robot.") and key.endswith(".state")


ROBOT_ROWS = 24  # more robots than this (a fleet) are counted by state, not listed one a line


def format_robots(st: health_pb2.CellStatus) -> list[str]:
    """What each robot is doing, from the robots services' heartbeats: a table of its own."""
    rows = []
    for s in st.services:
        for k, v in sorted(s.last.counters.items()):
            if _robot_state(k):
                code = int(v)
                what = ROBOT_STATES[code] if 0 <= code < len(ROBOT_STATES) else f"? (state {code})"
                rows.append((k[len("robot.") : -len(".state")], what))
    if not rows:
        return []
    if len(rows) > ROBOT_ROWS:  # a fleet: counted by state, a few named
        by: dict[str, list[str]] = {}
        for r, what in rows:
            by.setdefault(what, []).append(r)
        out = [f"ROBOTS  STATE ({len(rows)} robots, counted by state)"]
        for what, names in by.items():
            out.append(f"{len(names):>6}  {what}: {', '.join(names[:5])}{', ...' if len(names) > 5 else ''}")
        return out
    width = max(len("ROBOT"), *(len(r) for r, _ in rows))
    return [f"{'ROBOT':<{width}}  STATE", *(f"{r:<{width}}  {what}" for r, what in rows)]


def _link_counter(key: str) -> bool:
    return key.startswith(("rlink.L", "rlink.drops.", "rlink.event_latency"))


_LINK_FIELDS = ("packets_in", "packets_out", "bytes_in", "bytes_out", "overflow", "depth", "depth_max")


def format_links(st: health_pb2.CellStatus) -> list[str]:
    """The Responsive Link nodes' links (those that carried anything), drops and event latency."""
    head = ("NODE", "LINK", "KIND", "PKTS IN", "PKTS OUT", "BYTES IN", "BYTES OUT", "OVERFLOW", "DEPTH/MAX")
    rows, notes = [head], []
    for s in st.services:
        c = s.last.counters
        links: dict[tuple[str, str], dict[str, float]] = {}
        for key, v in c.items():
            parts = key.split(".")
            if (
                len(parts) == 4
                and parts[0] == "rlink"
                and parts[1].startswith("L")
                and parts[3] in _LINK_FIELDS
            ):
                links.setdefault((parts[1], parts[2]), {})[parts[3]] = v
        if not links:
            continue
        for (link, kind), f in sorted(links.items()):
            if not f.get("packets_in") and not f.get("packets_out"):
                continue
            depth = f"{_fmt_count(f.get('depth', 0))}/{_fmt_count(f.get('depth_max', 0))}"
            rows.append((s.name, link, kind, *(_fmt_count(f.get(k, 0)) for k in _LINK_FIELDS[:5]), depth))
        drops = {k.split(".")[-1]: v for k, v in c.items() if k.startswith("rlink.drops.") and v}
        dropped = ", ".join(f"{r} {_fmt_count(v)}" for r, v in sorted(drops.items())) or "none"
        lat = ""
        if "rlink.event_latency_p99_us" in c:
            p50, p99 = c["rlink.event_latency_p50_us"], c["rlink.event_latency_p99_us"]
            lat = f"; event arrival -> host p50 {p50:.0f} us, p99 {p99:.0f} us"
        notes.append(f"  {s.name}: drops {dropped}{lat}")
    if len(rows) == 1 and not notes:
        return []
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    table = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows]
    return ["Responsive Link", *table, *notes]
