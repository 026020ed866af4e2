"""A service's connection to the cell bus: publish, subscribe, request/reply.

Every node has one PUB socket and one control SUB socket (request replies,
requests it serves, sync pings), read by one reader task; each Subscription
has a SUB socket of its own so that data never queues behind control traffic.

No lost first messages: the forwarder subscribes its XSUB to everything, so a
publisher passes every message once its connection is up.  A node is ready
only when a ping it publishes has come back to it through the forwarder (on
the control socket at connect, on the new socket for each subscribe), which
proves both its publisher and its subscription are live end to end.

One module, over 600 lines, on purpose: publishing, subscribing and request/reply share the node's
sockets, its one reader task and its readiness handshake; the wire format is cell.bus.envelope's.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import itertools
import logging
import time
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, TypeVar, cast

import zmq
from google.protobuf.message import Message
from zmq.utils.monitor import parse_monitor_message

import cell.bus.curve as curve
import cell.bus.identity as identity
from cell import aio
from cell.bus.envelope import (
    Encoder,
    Envelope,
    EnvelopeError,
    GapCounter,
    Kind,
    check_topic,
    decode,
    frame_topic,
)
from cell.config import BusConfig
from cell.v1 import bus_pb2, health_pb2

log = logging.getLogger("cell.bus")
M = TypeVar("M", bound=Message)
Handler = Callable[[Any], Message | Awaitable[Message]]

_SYNC = b"_sync/"
_HANDSHAKE_FAILED = (
    zmq.EVENT_HANDSHAKE_FAILED_AUTH
    | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
    | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
)
_REPLY = "_reply/"
_SERVICE_EVENTS = "events/service/"  # the supervisors' word of a service started, failed, restarting
_GONE = (health_pb2.ServiceEvent.KIND_FAILED, health_pb2.ServiceEvent.KIND_RESTARTING)


class BusError(Exception):
    """Base of the bus's own errors."""


class BusUnavailable(BusError):
    """No forwarder answered: the cell (or its bus service) is not running at the configured endpoints."""


class BusRefused(BusUnavailable):
    """The forwarder refused this node: another cell's bus (or another start's), or a key it does
    not allow.  A service refused so ends (it is not of this cell); it is never let in by waiting."""


class BusTimeout(BusError, TimeoutError):
    """A request got no reply in time."""


class ServiceDown(BusTimeout):
    """A request's service failed while it waited (its supervisor said so on the bus): no reply will
    come.  What it asked may or may not have been done, as with a timeout; only known at once."""

    def __init__(self, service: str, method: str, why: str) -> None:
        self.service, self.method, self.why = service, method, why
        super().__init__(f"no reply from {service}.{method}: service {service!r} failed: {why}")


class FaultCode(StrEnum):
    """What a coded RPC error says (RpcFault.code, RemoteError.code, bus_pb2.RpcError.code on the
    wire): one list, so a caller's comparison names a code that exists; bus.proto's FaultCode
    is its source for other languages (tests/bus/test_proto.py holds the two equal)."""

    BAD_REQUEST = "bad_request"
    BUS_LOST = "bus_lost"
    BUSY = "busy"
    FAILED = "failed"
    IN_USE = "in_use"
    INTERNAL = "internal"
    NO_FRAME = "no_frame"
    PLAN = "plan"
    REFUSED = "refused"
    STOPPED = "stopped"
    TABLE_FULL = "table_full"
    TAKEN = "taken"
    TOO_MANY_JOINTS = "too_many_joints"
    UNKNOWN_METHOD = "unknown_method"
    UNKNOWN_MODULE = "unknown_module"
    UNKNOWN_ROBOT = "unknown_robot"
    UNKNOWN_TP = "unknown_tp"
    UNREACHABLE = "unreachable"


class RemoteError(BusError):
    """The serving side answered a request with an error."""

    def __init__(self, service: str, method: str, code: str, message: str) -> None:
        self.service, self.method, self.code, self.message = service, method, code, message
        super().__init__(f"{service}.{method} failed: {code}: {message}")


class RpcFault(Exception):
    """Raise in a request handler to answer with a coded error (a FaultCode; a data-plane table's
    refusal passes its own reason code on: cell.dataplane.tables.Refused)."""

    def __init__(self, code: FaultCode | str, message: str) -> None:
        self.code, self.message = code, message
        super().__init__(f"{code}: {message}")


def zmq_context() -> zmq.Context:
    """The process's one ZeroMQ context (inproc endpoints are shared within it)."""
    return zmq.Context.instance()


def secure_client(sock: zmq.Socket, config: BusConfig) -> None:
    """A node's socket: its CurveZMQ key (curve = true), else the cell and start it belongs to."""
    if config.curve:
        curve.secure_client(sock, config)
    else:
        identity.identify(sock, config.cell)


def secure_server(sock: zmq.Socket, config: BusConfig) -> None:
    """A forwarder's (or a link's) socket: CurveZMQ's server side, else it asks who a node is."""
    if config.curve:
        curve.secure_server(sock, config)
    else:
        identity.serve_identity(sock, config.cell)


def tune(sock: zmq.Socket, config: BusConfig) -> zmq.Socket:
    """The options every bus socket has: no linger, the configured HWM, and ZMTP heartbeats.

    Heartbeats are what gets a connection out of a stalled TCP stream: after a
    peer hung (SIGSTOP) with its receive window shut, Linux's zero-window probes
    back off so far that the stream stayed stuck for a minute after the peer came
    back (measured by `cell chaos`, bus-gone).  A connection that carries no PONG
    within the timeout is dropped, ZeroMQ connects anew (subscriptions included)
    and what was queued on the old one is lost, as the bus's gap counters say."""
    ms = round(config.heartbeat_s * 1000), round(config.heartbeat_timeout_s * 1000)
    for opt, value in (
        (zmq.LINGER, 0),
        (zmq.SNDHWM, config.hwm),
        (zmq.RCVHWM, config.hwm),
        (zmq.HEARTBEAT_IVL, ms[0]),
        (zmq.HEARTBEAT_TIMEOUT, ms[1]),
        (zmq.HEARTBEAT_TTL, ms[1]),
    ):
        sock.setsockopt(opt, value)
    return sock


_waiting: set[int] = set()
DROP_NEWS_S = 0.5  # a dropped bus connection is news only if no clean stop began within this
RECHECK_S = 0.1  # a waiter looks at EVENTS this often even if the FD never says so (see readable()):
# well inside the controller's 0.5 s verdict on a silent data plane (DEAD_S), which one lost edge at
# 0.5 s once reached (an RPC reply left waiting in the queue reads as a data plane gone)
# how often that happened, and how often a stale registration of the FD's number had to be cleared
wakeups = {"missed": 0, "stale": 0}


async def readable(sock: zmq.Socket) -> None:
    """Wait until sock has a message to receive, without blocking the event loop.

    ZeroMQ's FD only says "look at EVENTS" (it is edge-like), so EVENTS is
    checked before sleeping and on every wake-up.  A direct add_reader costs a
    fraction of zmq.asyncio's poll machinery on every bus hop.  One waiter per
    socket at a time.

    Two guards against a wake-up that never comes: ZeroMQ closes a socket's FD
    in its own thread, so the FD's number may come back for a new socket while
    the event loop still holds the old registration (asyncio would then only
    update its map and never tell epoll about the new file): any registration
    of the number is cleared first.  And EVENTS is looked at every RECHECK_S
    whatever the FD says, so that a lost edge costs at most that much, counted
    in `wakeups["missed"]`, never a subscriber asleep on a full queue.
    """
    if cast(int, sock.getsockopt(zmq.EVENTS)) & zmq.POLLIN:
        return
    loop = asyncio.get_running_loop()
    fut: asyncio.Future[None] = loop.create_future()
    fd = cast(int, sock.getsockopt(zmq.FD))  # (pyzmq types an option's value int | bytes)
    if fd in _waiting:
        raise RuntimeError("another coroutine is already waiting on this socket (one reader per socket)")
    _waiting.add(fd)

    def check() -> None:
        if fut.done() or sock.closed:  # (a wake-up queued before the socket was closed)
            return
        if cast(int, sock.getsockopt(zmq.EVENTS)) & zmq.POLLIN:
            fut.set_result(None)

    timer: asyncio.TimerHandle

    def recheck() -> None:
        nonlocal timer
        if fut.done() or sock.closed:
            return
        if cast(int, sock.getsockopt(zmq.EVENTS)) & zmq.POLLIN:
            wakeups["missed"] += 1
            fut.set_result(None)
        else:
            timer = loop.call_later(RECHECK_S, recheck)

    if loop.remove_reader(fd):  # a registration left by a closed socket whose FD had this number
        wakeups["stale"] += 1
    loop.add_reader(fd, check)
    timer = loop.call_later(RECHECK_S, recheck)
    try:
        check()  # a message may have come between the first look and add_reader
        await fut
    finally:
        timer.cancel()
        loop.remove_reader(fd)
        _waiting.discard(fd)


@dataclass(slots=True)
class _Waiting:
    fut: asyncio.Future[Envelope]
    service: str
    method: str


@dataclass(slots=True)
class _Method:
    request_type: type[Message]
    handler: Handler


class Subscription:
    """Messages on a set of topic prefixes, with loss counting; made by Bus.subscribe()."""

    def __init__(self, bus: Bus, sock: zmq.Socket, prefixes: tuple[str, ...]) -> None:
        self.prefixes = prefixes
        self.gaps = GapCounter()
        self.received = 0
        self.malformed = 0
        self._bus = bus
        self._sock = sock
        self._backlog: deque[bytes] = deque()
        self._ready: deque[Envelope] = deque()

    @property
    def lost(self) -> int:
        return self.gaps.lost

    def _drain(self, limit: int) -> list[Envelope]:
        # the hot loop of every subscriber: locals only, one decode per message
        out: list[Envelope] = []
        append, observe = out.append, self.gaps.observe
        backlog = self._backlog
        recv = self._sock.recv
        while len(out) < limit:
            if backlog:
                frame = backlog.popleft()
            else:
                try:
                    frame = recv(zmq.NOBLOCK)
                except zmq.Again:
                    break
            if frame.startswith(b"_"):  # the bus's own traffic (late sync pings; '' prefixes)
                continue
            try:
                env = decode(frame)
            except EnvelopeError as exc:
                self.malformed += 1
                log.debug("dropped malformed message %r: %s", frame[:64], exc)
                continue
            observe(env.instance, env.topic, env.seq)
            append(env)
        self.received += len(out)
        return out

    async def recv_batch(self, max_messages: int = 1024, timeout: float | None = None) -> list[Envelope]:
        """The messages waiting (up to max_messages); waits for one at least, TimeoutError after timeout."""
        if self._ready:
            out = list(self._ready)
            self._ready.clear()
            return out
        out = self._drain(max_messages)
        async with asyncio.timeout(timeout):
            while not out:
                await readable(self._sock)
                out = self._drain(max_messages)
        return out

    async def recv(self, timeout: float | None = None) -> Envelope:
        if not self._ready:
            self._ready.extend(await self.recv_batch(timeout=timeout))
        return self._ready.popleft()

    def __aiter__(self) -> AsyncIterator[Envelope]:
        return self._iter()

    def decoded(self, cls: type[M], batch: list[Envelope]) -> list[M]:
        """The `cls` messages of a batch: other types are passed over, and a payload that does not
        parse is counted malformed and dropped (no peer's message may end a subscriber)."""
        want, out = cls.DESCRIPTOR.full_name, []
        for env in batch:
            if env.type_name != want:
                continue
            try:
                out.append(env.decode(cls))
            except EnvelopeError as exc:
                self.malformed += 1
                log.debug("dropped %s: %s", want, exc)
        return out

    async def recv_messages(self, cls: type[M], timeout: float | None = None) -> list[M]:
        """The `cls` messages waiting (see decoded()); waits for one message at least."""
        return self.decoded(cls, await self.recv_batch(timeout=timeout))

    async def messages(self, cls: type[M]) -> AsyncIterator[M]:
        """Every `cls` message, one by one, until cancelled."""
        while True:
            for m in await self.recv_messages(cls):
                yield m

    async def _iter(self) -> AsyncIterator[Envelope]:
        while True:
            yield await self.recv()

    def close(self) -> None:
        if not self._sock.closed:
            self._sock.close(linger=0)
        if self in self._bus._subs:
            self._bus._subs.remove(self)
            retired = self._bus._retired  # its counts stay in the node's totals
            retired["received"] += self.received
            retired["lost"] += self.lost
            retired["malformed"] += self.malformed + self.gaps.implausible


class Bus:
    """One node on the bus, named `source`; open it with `async with Bus.connect(cfg, name) as bus`."""

    _pub: zmq.Socket  # (connect() opens both)
    _ctl: zmq.Socket

    def __init__(self, config: BusConfig, source: str) -> None:
        self.config = config
        self.source = source
        self._enc = Encoder(source)
        self.instance = self._enc.instance
        self._reply_topic = f"{_REPLY}{self.instance:08x}"
        self._topics: dict[str, bytes] = {}
        self._pending: dict[int, _Waiting] = {}  # correlation -> the request waiting for its reply
        self._down: dict[str, str] = {}  # service -> why, from its supervisor's events (until it starts)
        self._methods: dict[str, _Method] = {}
        self._syncs: dict[bytes, asyncio.Future[None]] = {}
        self._corr = itertools.count(1)
        self._tokens = itertools.count(1)
        self._subs: list[Subscription] = []
        # counts of closed subscriptions: heartbeat counters never go backwards
        self._retired = {"received": 0, "lost": 0, "malformed": 0}
        self._handlers: set[asyncio.Task[None]] = set()
        self._reader: asyncio.Task[None] | None = None
        self._watchers: list[asyncio.Task[None]] = []
        self._monitors: list[tuple[zmq.Socket, zmq.Socket]] = []  # (watched socket, its monitor)
        self.disconnects = 0  # drops of the connection to the forwarder (both sockets' at once: one)
        self._dropped_at = -1e9  # monotonic s of the last drop counted
        self.refused = ""  # why the forwarder refused us, if it did (CurveZMQ, or the cell's identity)
        self._refused_for_good = False  # (a refusal; not a handshake cut short, which may go through)
        self.published = 0
        self.dropped = 0
        self.requests = 0
        self.served = 0
        self.late_replies = 0
        self.held_replies = 0  # replies found queued once the request's timer was seen (see request())
        self.malformed = 0
        self.patient = False  # see connect(wait=False)
        self._ctl_live = False  # a ping has come back on the control socket: replies will reach us
        self.joined = False  # it has been on the bus (a drop before that is a failure to connect: said so)

    # --- lifetime ----------------------------------------------------------------------------

    @classmethod
    @contextlib.asynccontextmanager
    async def connect(cls, config: BusConfig, source: str, *, wait: bool = True) -> AsyncIterator[Bus]:
        """Connect, wait until the bus carries our messages both ways, yield; close everything on exit.

        wait=False (services under a supervisor) yields at once and never gives up: the node's
        subscribe() and serve() wait for the forwarder however long it is away, publishing meanwhile
        drops, so a service serves its own sockets whether or not the bus is up yet."""
        bus = cls(config, source)
        bus.patient = not wait
        ctx = zmq_context()
        bus._pub = tune(ctx.socket(zmq.PUB), config)
        bus._ctl = tune(ctx.socket(zmq.SUB), config)
        try:
            secure_client(bus._pub, config)
            secure_client(bus._ctl, config)
            bus._pub.connect(config.pub)
            bus._ctl.subscribe(bus._reply_topic.encode())
            bus._ctl.subscribe(_SYNC + f"{bus.instance:08x}/c".encode())
            bus._ctl.subscribe(_SERVICE_EVENTS.encode())
            bus._ctl.connect(config.sub)
            # the node owns its reader and handler tasks (no TaskGroup here: it would wrap
            # the caller's own exceptions in ExceptionGroups); they are awaited on the way out
            bus._reader = asyncio.create_task(bus._read_control(), name=f"bus-reader:{source}")
            gone = zmq.EVENT_DISCONNECTED
            for sock, events in ((bus._pub, gone | _HANDSHAKE_FAILED), (bus._ctl, gone | _HANDSHAKE_FAILED)):
                mon = sock.get_monitor_socket(events)
                bus._monitors.append((sock, mon))
                watch = bus._watch_connection(mon)
                bus._watchers.append(asyncio.create_task(watch, name=f"bus-watch:{source}"))
            if wait:
                await bus._sync_control()
            yield bus
        finally:
            await bus._stop_tasks()
            bus._close()

    async def _watch_connection(self, mon: zmq.Socket) -> None:
        """A connection to the forwarder dropped (it died, or a heartbeat went unanswered): a
        request or a reply on its way then was lost with it, so every request waiting is answered
        now (RemoteError, code bus_lost), not with a timeout much later.  Either way (the request
        path or the reply path) the next request first proves the path anew with a sync ping: a
        request sent while the new connection has not yet carried its subscriptions would be lost
        without a word."""
        while True:
            await readable(mon)
            while True:
                try:
                    frames = mon.recv_multipart(zmq.NOBLOCK)
                except zmq.Again:
                    break
                event = parse_monitor_message(frames)["event"]
                if event & _HANDSHAKE_FAILED:
                    if self.config.curve:
                        self.refused = "the bus refused this node's CurveZMQ key (not in its allow-list?)"
                    else:  # (cell.bus.identity: the forwarder's log and forwarder.refused say which)
                        member = " (a member of a `cell up` of its own)" if identity.member_token() else ""
                        self.refused = (
                            f"the bus at {self.config.sub} refused this node of cell {self.config.cell!r}"
                            f"{member}: it is another cell's bus, or another start's of this cell"
                        )
                    self._refused_for_good = event != zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
                    if not self._refused_for_good:
                        self.refused = (
                            "the handshake with the bus failed: it went away mid-handshake, or the "
                            "curve settings differ (this node: curve = "
                            f"{'true' if self.config.curve else 'false'})"
                        )
                    # (a node that gives up says it in its error; one that waits on, here)
                    log.log(
                        logging.WARNING if self.patient else logging.DEBUG,
                        "%s: %s",
                        self.source,
                        self.refused,
                    )
                elif event == zmq.EVENT_DISCONNECTED:
                    self._ctl_live = False
                    n = self.abandon(
                        None, "bus_lost", "the bus connection dropped; it may or may not have been done"
                    )
                    now = time.monotonic()
                    if now - self._dropped_at < 1.0 and n == 0:
                        continue  # (the node's other socket telling of the same drop)
                    self._dropped_at = now
                    self.disconnects += 1
                    # (not news unless it cost answers: a clean stop, where the bus goes as everything
                    # goes; a refusal said already; a client's failure to connect, said in its error)
                    quiet = (self.refused or not (self.joined or self.patient)) and n == 0
                    if n or quiet:
                        self._say_dropped(n, quiet)
                    else:  # (a clean stop's SIGTERM can reach this process just after the bus went)
                        asyncio.get_running_loop().call_later(DROP_NEWS_S, self._say_dropped, n, False)

    def _say_dropped(self, n: int, quiet: bool) -> None:
        """Log a dropped bus connection: a warning unless it is expected: nothing was lost by it, or
        the process is stopping (a clean stop, where the bus goes as everything goes: a controller's
        watch on the data plane has a read out most of the time, and it goes too)."""
        quiet = (quiet and n == 0) or aio.shutting_down()
        log.log(
            logging.DEBUG if quiet else logging.WARNING,
            "%s: the bus connection dropped (%d waiting request(s) answered)",
            self.source,
            n,
        )

    async def _stop_tasks(self) -> None:
        tasks = [t for t in (self._reader, *self._watchers, *self._handlers) if t is not None]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    def _close(self) -> None:
        for sub in list(self._subs):
            sub.close()
        for sock, mon in self._monitors:
            with contextlib.suppress(zmq.ZMQError):
                sock.disable_monitor()
            mon.close(linger=0)
        for sock in (self._pub, self._ctl):
            if not sock.closed:
                sock.close(linger=0)
        for w in self._pending.values():
            w.fut.cancel()

    def counters(self) -> dict[str, float]:
        """What this node has done so far, for heartbeats."""
        old = self._retired
        return {
            "bus.published": self.published,
            "bus.dropped": self.dropped,
            "bus.received": old["received"] + sum(s.received for s in self._subs),
            "bus.lost": old["lost"] + sum(s.lost for s in self._subs),
            # (an envelope whose sequence number its stream refutes is as bad as one that does not parse)
            "bus.malformed": self.malformed
            + old["malformed"]
            + sum(s.malformed + s.gaps.implausible for s in self._subs),
            "bus.requests": self.requests,
            "bus.served": self.served,
            "bus.late_replies": self.late_replies,
            "bus.held_replies": self.held_replies,
            "bus.disconnects": self.disconnects,
            "bus.missed_wakeups": wakeups["missed"],  # (the process's, all its nodes together)
        }

    # --- sync: prove a path end to end -------------------------------------------------------

    async def _sync(self, name: str, wait: Callable[[bytes], Awaitable[None]]) -> None:
        token = _SYNC + f"{self.instance:08x}/{name}".encode()
        done = asyncio.ensure_future(wait(token))
        delay = 0.0005
        deadline = asyncio.get_running_loop().time() + self.config.connect_timeout_s
        warned = False
        try:
            while not done.done():
                if self._refused_for_good:
                    raise BusRefused(self.refused)  # (never joins: waiting would not change that)
                if asyncio.get_running_loop().time() > deadline:
                    if not self.patient:
                        why = self.refused or "is the cell's 'bus' service running?"
                        raise BusUnavailable(
                            f"no bus forwarder answered at {self.config.pub} / {self.config.sub} within "
                            f"{self.config.connect_timeout_s:g} s ({why})"
                        )
                    if not warned:
                        log.warning("%s: waiting for the bus forwarder at %s", self.source, self.config.sub)
                        warned = True
                with contextlib.suppress(zmq.Again):
                    self._pub.send(token + b"\0", zmq.NOBLOCK)
                await asyncio.wait([done], timeout=delay)
                delay = min(delay * 2, 0.05 if not warned else 0.25)
            await done
        finally:
            done.cancel()

    async def _sync_control(self) -> None:
        await self._sync(f"c{next(self._tokens)}", self._ctl_token_wait)
        self._ctl_live = self.joined = True

    async def _ctl_token_wait(self, token: bytes) -> None:
        fut = self._syncs[token] = asyncio.get_running_loop().create_future()
        try:
            await fut
        finally:
            del self._syncs[token]

    # --- publish / subscribe -----------------------------------------------------------------

    def _topic(self, topic: str) -> bytes:
        raw = self._topics.get(topic)
        if raw is None:
            raw = check_topic(topic)
            if len(self._topics) < 10_000:
                self._topics[topic] = raw
        return raw

    def _send(self, topic: bytes, msg: Message, kind: Kind = Kind.PUBLISH, correlation: int = 0) -> None:
        self._send_raw(topic, msg.DESCRIPTOR.full_name, msg.SerializeToString(), kind, correlation)

    def _send_raw(
        self, topic: bytes, type_name: str, payload: bytes, kind: Kind = Kind.PUBLISH, correlation: int = 0
    ) -> None:
        frame = self._enc.encode(topic, type_name, payload, kind, correlation)
        try:
            self._pub.send(frame, zmq.NOBLOCK)
        except zmq.Again:
            self.dropped += 1
        else:
            self.published += 1

    def publish(self, topic: str, msg: Message) -> None:
        """Send msg on topic to every subscriber of a prefix of it; never blocks (drops at the HWM)."""
        self._send(self._topic(topic), msg)

    def publish_serialized(self, topic: str, type_name: str, payload: bytes) -> None:
        """publish() of a message serialized already (payload: a `type_name`'s bytes, as protobuf
        encodes them): for messages built in C (cell.robot.truthcodec)."""
        self._send_raw(self._topic(topic), type_name, payload)

    async def subscribe(self, *prefixes: str) -> Subscription:
        """A Subscription to topics starting with any of prefixes ('' is everything), live on return."""
        raw = [check_topic(p) if p else b"" for p in prefixes] or [b""]
        sock = tune(zmq_context().socket(zmq.SUB), self.config)
        secure_client(sock, self.config)
        for p in raw:
            sock.subscribe(p)
        sub = Subscription(self, sock, tuple(prefixes))
        self._subs.append(sub)
        try:
            sock.connect(self.config.sub)

            async def wait(token: bytes) -> None:
                sock.subscribe(token)
                while True:
                    await readable(sock)
                    while True:
                        try:
                            frame = sock.recv(zmq.NOBLOCK)
                        except zmq.Again:
                            break
                        if frame_topic(frame) == token:
                            sock.unsubscribe(token)
                            return
                        sub._backlog.append(frame)

            await self._sync(f"s{next(self._tokens)}", wait)
        except BaseException:
            sub.close()
            raise
        return sub

    # --- request / reply ---------------------------------------------------------------------

    async def request(
        self,
        service: str,
        method: str,
        msg: Message,
        reply_type: type[M] | None = None,
        timeout: float | None = None,
    ) -> M | Message:
        """Ask `service` to run `method`; its reply, or BusTimeout (ServiceDown, at once, if its
        supervisor says it failed meanwhile), or RemoteError if it answered an error."""
        timeout = self.config.request_timeout_s if timeout is None else timeout
        if not self._ctl_live:  # connected without waiting: a reply could go nowhere until then
            try:
                async with asyncio.timeout(timeout):
                    await self._sync_control()
            except TimeoutError:
                raise BusTimeout(f"no bus to reach {service}.{method} within {timeout:g} s") from None
        corr = next(self._corr)
        fut: asyncio.Future[Envelope] = asyncio.get_running_loop().create_future()
        self._pending[corr] = _Waiting(fut, service, method)
        self.requests += 1
        try:
            self._send(self._topic(f"rpc/{service}/{method}"), msg, Kind.REQUEST, corr)
            # (asyncio.wait, not asyncio.timeout: the future must outlive the deadline, see below)
            done, _ = await asyncio.wait((fut,), timeout=timeout)
            if not done and not self._ctl.closed:
                # a reply already queued here counts: a loop held up past the deadline (a controller
                # busy with a fleet's thousand arms) sees its timers before the replies that beat them,
                # and would read a data plane that answered in milliseconds as silent
                self._drain_control()
                if fut.done():
                    self.held_replies += 1
            if not fut.done():
                why = self._down.get(service, "")
                state = f"service {service!r} is down: {why}" if why else f"is service {service!r} running?"
                raise BusTimeout(f"no reply from {service}.{method} within {timeout:g} s ({state})")
            env = fut.result()  # (or ServiceDown, RemoteError: the service's failure, as it came)
        finally:
            self._pending.pop(corr, None)
            fut.cancel()  # (a no-op once done: a caller cancelled mid-wait leaves nothing behind)
        if env.kind == Kind.ERROR:
            err = env.decode(bus_pb2.RpcError)
            raise RemoteError(service, method, err.code, err.message)
        return env.decode(reply_type) if reply_type is not None else env.message()

    def abandon(self, service: str | None, code: str, reason: str) -> int:
        """Answer every request waiting on `service` (None: on any) with RemoteError(code, reason) now,
        rather than a timeout later (the serving process is known to have died); how many there were."""
        n = 0
        for w in list(self._pending.values()):
            if service in (None, w.service) and not w.fut.done():
                w.fut.set_exception(RemoteError(w.service, w.method, code, reason))
                n += 1
        return n

    async def serve(self, service: str, methods: Mapping[str, tuple[type[Message], Handler]]) -> None:
        """Answer requests to service.<method>; handlers may be sync or async and may raise RpcFault."""
        for name, (request_type, handler) in methods.items():
            self._methods[f"rpc/{service}/{name}"] = _Method(request_type, handler)
        self._ctl.subscribe(check_topic(f"rpc/{service}/"))
        await self._sync_control()

    # --- the control reader ------------------------------------------------------------------

    async def _read_control(self) -> None:
        while True:
            await readable(self._ctl)
            self._drain_control()

    def _drain_control(self) -> None:
        """Dispatch every control message queued now (replies, requests, syncs), without waiting."""
        recv = self._ctl.recv
        while True:
            try:
                frame = recv(zmq.NOBLOCK)
            except zmq.ZMQError:  # (Again: nothing more queued; or the socket closed under a late look)
                return
            try:
                self._dispatch(frame)
            except Exception:  # a bug here must not silence the node: log it and go on
                self.malformed += 1
                log.exception("%s: control message %r not handled", self.source, frame[:64])

    def _dispatch(self, frame: bytes) -> None:
        if frame.startswith(_SYNC):
            sync = self._syncs.get(frame_topic(frame))
            if sync is not None and not sync.done():
                sync.set_result(None)
            return
        try:
            env = decode(frame)
        except EnvelopeError as exc:
            self.malformed += 1
            log.debug("%s: dropped malformed control message: %s", self.source, exc)
            return
        if env.topic == self._reply_topic:
            waiting = self._pending.pop(env.correlation, None)
            fut = None if waiting is None else waiting.fut
            if fut is None or fut.done():
                self.late_replies += 1
            elif env.kind in (Kind.REPLY, Kind.ERROR):
                fut.set_result(env)
            return
        if env.topic.startswith(_SERVICE_EVENTS):
            self._service_event(env)
            return
        if env.kind != Kind.REQUEST:
            return
        task = asyncio.create_task(self._serve_one(env))
        self._handlers.add(task)
        task.add_done_callback(self._handlers.discard)

    def _service_event(self, env: Envelope) -> None:
        """A supervisor's word: a service that failed (restarting or not) answers no request waiting
        on it, so each ends now (ServiceDown, with the service's error); a request timing out while
        it is down says so."""
        try:
            if env.type_name != health_pb2.ServiceEvent.DESCRIPTOR.full_name:
                raise EnvelopeError(f"a {env.type_name or 'nothing'} on {env.topic!r}")
            ev = env.decode(health_pb2.ServiceEvent)
        except EnvelopeError:
            self.malformed += 1
            return
        if ev.kind in _GONE:
            if len(self._down) < 256 or ev.service in self._down:  # (a peer's names are not ours to keep)
                self._down[ev.service] = ev.text
            for w in self._pending.values():
                if w.service == ev.service and not w.fut.done():
                    w.fut.set_exception(ServiceDown(w.service, w.method, ev.text))
        elif ev.kind == health_pb2.ServiceEvent.KIND_STARTED:
            self._down.pop(ev.service, None)

    async def _serve_one(self, env: Envelope) -> None:
        reply_to = f"{_REPLY}{env.instance:08x}".encode()
        corr = env.correlation
        method = self._methods.get(env.topic)
        try:
            if method is None:
                raise RpcFault(FaultCode.UNKNOWN_METHOD, f"no method {env.topic.removeprefix('rpc/')!r} here")
            want = method.request_type.DESCRIPTOR.full_name
            if env.type_name != want:
                raise RpcFault(
                    FaultCode.BAD_REQUEST, f"expected a {want}, got a {env.type_name or 'nothing'}"
                )
            result = method.handler(env.decode(method.request_type))
            if inspect.isawaitable(result):
                result = await result
            kind = Kind.REPLY
        except RpcFault as fault:
            result, kind = bus_pb2.RpcError(code=fault.code, message=fault.message), Kind.ERROR
        except EnvelopeError as exc:
            result, kind = bus_pb2.RpcError(code=FaultCode.BAD_REQUEST, message=str(exc)), Kind.ERROR
        except Exception as exc:
            log.exception("%s: handler for %s failed", self.source, env.topic)
            result = bus_pb2.RpcError(code=FaultCode.INTERNAL, message=f"{type(exc).__name__}: {exc}")
            kind = Kind.ERROR
        if not self._ctl_live:  # our connection was made anew since: a reply sent before the forwarder
            # has subscribed to it would be lost without a word (the requester waits out its timeout)
            with contextlib.suppress(TimeoutError, BusError):
                async with asyncio.timeout(self.config.request_timeout_s):
                    await self._sync_control()
        self._send(reply_to, result, kind, corr)
        self.served += 1
