"""The cell's status: the launcher keeps every service's last heartbeat and answers `cell.status`.

`cell status` is then one request away, instead of waiting a heartbeat period
to hear every service; services another host runs show up as soon as their
heartbeats arrive.
"""

from __future__ import annotations

import time

from cell.bus import Bus
from cell.v1 import health_pb2

POLL_TOPIC = "health-poll"  # supervisors answer a message here with their heartbeats at once
STALE_AFTER = 2.5  # heartbeat periods without news before a service is "stale"
_HEALTH = {
    health_pb2.SERVICE_STATE_STARTING: "starting",
    health_pb2.SERVICE_STATE_RUNNING: "ok",
    health_pb2.SERVICE_STATE_BACKOFF: "backoff",
    health_pb2.SERVICE_STATE_FAILED: "failed",
    health_pb2.SERVICE_STATE_STOPPED: "stopped",
}


class StatusRegistry:
    def __init__(self, cell: str, mode: str, expected: list[str]) -> None:
        self.cell = cell
        self.mode = mode
        self.expected = list(expected)
        self.started = time.monotonic()
        self._last: dict[str, tuple[health_pb2.Heartbeat, float]] = {}
        self._process_restarts: dict[str, tuple[int, str]] = {}  # process -> (restarts, why)

    def process_restarted(self, process: str, why: str) -> None:
        """A process the launcher runs died and was started again: its services' restarts count it
        (their new supervisor starts counting from 0)."""
        n, _ = self._process_restarts.get(process, (0, ""))
        self._process_restarts[process] = (n + 1, why)

    def observe(self, hb: health_pb2.Heartbeat, at: float | None = None) -> None:
        self._last[hb.service] = (hb, time.monotonic() if at is None else at)

    def status(self, _request: object = None) -> health_pb2.CellStatus:
        now = time.monotonic()
        out = health_pb2.CellStatus(cell=self.cell, mode=self.mode, uptime_s=now - self.started)
        names = self.expected + sorted(set(self._last) - set(self.expected))
        for name in names:
            entry = out.services.add(name=name)
            if name not in self._last:
                entry.health = "missing"
                continue
            hb, at = self._last[name]
            entry.last.CopyFrom(hb)
            if hb.process in self._process_restarts:
                n, why = self._process_restarts[hb.process]
                entry.last.restarts += n
                entry.last.last_error = entry.last.last_error or why
            entry.heartbeat_age_s = now - at
            stale = entry.heartbeat_age_s > STALE_AFTER * max(hb.interval_s, 0.1)
            alive = hb.state not in (health_pb2.SERVICE_STATE_FAILED, health_pb2.SERVICE_STATE_STOPPED)
            entry.health = "stale" if stale and alive else _HEALTH.get(hb.state, "unknown")
        return out

    async def run(self, bus: Bus) -> None:
        """Serve `cell.status` and keep up with heartbeats until cancelled."""
        health = await bus.subscribe("health/")
        await bus.serve("cell", {"status": (health_pb2.StatusRequest, self.status)})
        bus.publish(POLL_TOPIC, health_pb2.StatusRequest())  # no waiting a whole period to hear everyone
        while True:
            for env in await health.recv_batch():
                if env.type_name == health_pb2.Heartbeat.DESCRIPTOR.full_name:
                    self.observe(env.decode(health_pb2.Heartbeat))


def _fmt_count(v: float) -> str:
    if v == int(v):
        return f"{int(v)}"
    return f"{v:.3g}"


def format_status(st: health_pb2.CellStatus, counters: bool = True) -> str:
    """A table for people: one row per service, counters below it."""
    lines = [f"cell {st.cell!r} (layout {st.mode}), up {st.uptime_s:.1f} s"]
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
        if s.health == "missing":
            rows.append((s.name, "missing", "-", "-", "-", "-", "-", "-", "never", ""))
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
    if counters:
        for s in st.services:
            if s.last.counters:
                items = sorted(s.last.counters.items())
                lines.append(f"  {s.name}: " + ", ".join(f"{k}={_fmt_count(v)}" for k, v in items))
    return "\n".join(lines)
