"""Run a process's services: restart policy, heartbeats and lifecycle events.

Each service runs in its own task under one TaskGroup.  A service that raises
is logged with its traceback and then either restarted with exponential
backoff or, with on_failure = "stop", ends the whole cell (ServiceFailed);
it never dies silently.  Heartbeats and events go out through the
supervisor's own bus node, so a service that is down is still reported.
Each heartbeat carries the service's share of the event loop
(`busy_ms_per_s`, cell/meter.py), its process's CPU time per second
(`process.cpu_ms_per_s`, all threads) and how the OS schedules that process.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections import deque
from collections.abc import Awaitable

from cell import aio, meter, rtbudget, sched
from cell.bus import Bus, BusError
from cell.config import MAIN_GROUP, CellConfig
from cell.service import ServiceContext, ServiceSpec
from cell.status import POLL_TOPIC, host_name
from cell.v1 import health_pb2

log = logging.getLogger("cell.supervisor")
LONG_STEP_MS = 5.0  # a real-time service's loop held this long in one step is logged (cell up --verbose)
State = health_pb2.ServiceState
Event = health_pb2.ServiceEvent


class ServiceFailed(Exception):
    """A service failed and the policy says the cell stops."""

    def __init__(self, name: str, error: str, what: str = "service") -> None:
        self.name, self.error = name, error
        super().__init__(f"{what} {name!r} failed: {error}")


class ServiceRunner:
    """One service under the restart policy, and what its heartbeat says about it."""

    def __init__(self, spec: ServiceSpec, config: CellConfig, supervisor: Supervisor) -> None:
        self.spec = spec
        self.config = config
        self._sup = supervisor
        self.state = State.SERVICE_STATE_STARTING
        self.restarts = 0
        self.last_error = ""
        self.started = time.monotonic()
        self.ctx: ServiceContext | None = None
        self.account = meter.Account(spec.name)
        self._busy = meter.Rate(0.8 * config.services.heartbeat_s)

    @property
    def name(self) -> str:
        return self.spec.name

    async def run(self) -> None:
        meter.charge_to(self.account)  # this task and every task the service starts
        policy = self.config.services
        backoff = policy.backoff_initial_s
        while True:
            self.state = State.SERVICE_STATE_STARTING
            self.started = time.monotonic()
            try:
                await self._run_once()
            except asyncio.CancelledError:
                self.state = State.SERVICE_STATE_STOPPED
                raise
            except Exception as exc:
                ran = time.monotonic() - self.started
                self.last_error = f"{type(exc).__name__}: {exc}"
                log.error("service %r failed after %.1f s", self.name, ran, exc_info=exc)
                if policy.on_failure == "stop":
                    self._change(State.SERVICE_STATE_FAILED, Event.KIND_FAILED, self.last_error)
                    raise ServiceFailed(self.name, self.last_error) from exc
                if ran > policy.backoff_max_s:  # it had been healthy for a while: start over gently
                    backoff = policy.backoff_initial_s
                self.restarts += 1
                self._change(
                    State.SERVICE_STATE_BACKOFF,
                    Event.KIND_RESTARTING,
                    f"{self.last_error}; restart {self.restarts} in {backoff:.1f} s",
                )
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, policy.backoff_max_s)
            else:
                self._change(State.SERVICE_STATE_STOPPED, Event.KIND_STOPPED, "finished")
                return

    async def _run_once(self) -> None:
        async with contextlib.AsyncExitStack() as stack:
            bus = None
            if self.spec.needs_bus:
                # never held up by the bus: a service serves its own sockets from the start
                bus = await stack.enter_async_context(Bus.connect(self.config.bus, self.name, wait=False))
            self.ctx = ServiceContext(
                self.name,
                self.config,
                bus,
                lambda: self._change(State.SERVICE_STATE_RUNNING, Event.KIND_STARTED),
            )
            if self.spec.ready_on_start:
                self.ctx.ready()
            await self.spec.run(self.ctx)

    def _change(self, state: State, kind: Event.Kind, text: str = "") -> None:
        self.state = state
        self._sup.event(self, kind, text)

    def heartbeat(self, process: dict[str, float], placement: str) -> health_pb2.Heartbeat:
        counters: dict[str, float] = dict(process)
        if self.ctx is not None:
            counters.update(self.ctx.counters)
            if self.ctx.has_bus:
                counters.update(self.ctx.bus.counters())
        busy_ms = self.account.busy_ns / 1e6
        counters["busy_s"] = busy_ms / 1e3  # since the process started (restarts included)
        if (busy := self._busy.update(busy_ms)) is not None:
            counters["busy_ms_per_s"] = busy
        # the longest the service held its loop in one go since the last heartbeat (a real-time
        # service: what delays its next tick), and in which coroutine, logged when past a tick
        longest_ms, where = self.account.take_longest()
        counters["busy_step_max_ms"] = longest_ms
        if longest_ms > LONG_STEP_MS and sched.realtime():
            log.info("service %s held its loop %.1f ms in one step (%s)", self.name, longest_ms, where)
        return health_pb2.Heartbeat(
            service=self.name,
            host=host_name(self.config),
            pid=os.getpid(),
            state=self.state,
            uptime_s=time.monotonic() - self.started,
            restarts=self.restarts,
            last_error=self.last_error,
            counters=counters,
            interval_s=self.config.services.heartbeat_s,
            process=self._sup.process,
            sched=placement,
        )


class Supervisor:
    """Runs a set of services in this process until stopped."""

    def __init__(
        self,
        config: CellConfig,
        specs: list[ServiceSpec],
        node_name: str | None = None,
        process: str = MAIN_GROUP,
    ) -> None:
        self.config = config
        self.process = process
        self.runners = [ServiceRunner(spec, config, self) for spec in specs]
        self.node_name = node_name or f"supervisor-{os.getpid()}"
        self._cpu = meter.Rate(0.8 * config.services.heartbeat_s)
        self._bus: Bus | None = None
        self._wake = asyncio.Event()
        self._events: deque[tuple[str, health_pb2.ServiceEvent]] = deque(maxlen=256)

    def runner(self, name: str) -> ServiceRunner:
        return next(r for r in self.runners if r.name == name)

    async def run(self, stop: asyncio.Event) -> None:
        """Run every service until `stop` is set; raises ServiceFailed if the policy stops the cell."""
        meter.install(asyncio.get_running_loop())
        try:
            async with asyncio.TaskGroup() as tg:
                services = [tg.create_task(r.run(), name=f"service:{r.name}") for r in self.runners]
                beats = tg.create_task(self._heartbeats(), name="heartbeats")
                await stop.wait()
                aio.begin_shutdown()
                for task in services:
                    task.cancel()
                await asyncio.gather(*services, return_exceptions=True)
                self._publish_heartbeats()  # the last word: every service STOPPED
                beats.cancel()
        except* ServiceFailed as group:
            raise group.exceptions[0] from None

    def event(self, runner: ServiceRunner, kind: Event.Kind, text: str) -> None:
        ev = health_pb2.ServiceEvent(service=runner.name, kind=kind, text=text, restarts=runner.restarts)
        self._events.append((f"events/service/{runner.name}", ev))
        self._flush_events()
        self._wake.set()  # heartbeats go out now, not at the next tick

    def _flush_events(self) -> None:
        while self._bus is not None and self._events:
            topic, ev = self._events.popleft()
            self._bus.publish(topic, ev)

    def _publish_heartbeats(self) -> None:
        if self._bus is None:
            return
        cpu_s = sched.cpu_seconds()
        process = {"process.cpu_s": cpu_s}
        if (cpu := self._cpu.update(cpu_s * 1e3)) is not None:
            process["process.cpu_ms_per_s"] = cpu
        if meter.HELD is not None:  # (a real-time process: the kernel's RT throttling, seen)
            process.update(meter.HELD.counters("process.rt."))
        process.update(rtbudget.counters("process.rt."))  # (its Python's real-time budget, if it has one)
        placement = sched.describe()
        for r in self.runners:
            self._bus.publish(f"health/{r.name}", r.heartbeat(process, placement))

    async def _heartbeats(self) -> None:
        interval = self.config.services.heartbeat_s
        while True:
            try:
                async with Bus.connect(self.config.bus, self.node_name) as bus:
                    poll = await bus.subscribe(POLL_TOPIC)
                    self._bus = bus
                    try:
                        self._flush_events()
                        while True:
                            self._publish_heartbeats()
                            self._wake.clear()
                            await _first(self._wake.wait(), poll.recv_batch(), timeout=interval)
                    finally:
                        self._bus = None
            except BusError as exc:
                log.warning("%s: heartbeats paused: %s", self.node_name, exc)
                await asyncio.sleep(interval)


async def _first(*aws: Awaitable[object], timeout: float) -> None:
    """Wait until any of aws completes or timeout passes; cancel the rest."""
    tasks = [asyncio.ensure_future(a) for a in aws]
    try:
        await asyncio.wait(tasks, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
