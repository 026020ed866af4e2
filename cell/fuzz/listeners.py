"""The fuzz campaign's listeners: each of a running cell's sockets fed generated bad inputs in bursts,
each burst followed by a probe (a valid request on the same path) that must be answered in time."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zmq
import zmq.asyncio

from cell.bus import Bus, BusTimeout, FaultCode, RemoteError
from cell.bus.envelope import Encoder, EnvelopeError
from cell.bus.envelope import Kind as BusKind
from cell.bus.envelope import decode as decode_frame
from cell.bus.node import secure_client
from cell.config import CellConfig, ConfigError, config_from_text, load_config, parse_host_port
from cell.fuzz import strategies
from cell.fuzz import ur as ur_fuzz
from cell.fuzz.mutate import Mutator
from cell.rlink import packet as rlp
from cell.rlink.cellnet import Topology
from cell.robot import datagram, udp
from cell.robot.datagram import Kind
from cell.skills.protocol import Command, CommandReader, Done, Error, ErrorCode, parse_reply
from cell.snp import packet as snp
from cell.v1 import controller_pb2, dataplane_pb2, health_pb2, robot_pb2

PROBE_ROBOT = 65000  # a robot id no cell configures: the data plane tells it to hold
SEEDS = 600  # hypothesis examples per format
HANG_S = 5.0  # a probe not answered within this is a hang
RESEND_S = 0.5  # a UDP probe is sent again after this without its answer
BUS_RESEND_S = 1.0  # a bus probe likewise (a reply can take longer: it crosses two processes)
SAFE_RLINK = {rlp.EventType.NOP, rlp.EventType.ECHO, rlp.EventType.ECHO_REPLY}
# bus topics whose subscribers would believe a well-formed message (its type, as they decode it)
TRUSTING = {
    "health/": health_pb2.Heartbeat,
    "truth/": robot_pb2.RobotTruth,
    "plan/": controller_pb2.Plan,
    "announce/robot/": robot_pb2.RobotAnnounce,
    "events/": robot_pb2.RobotEvent,
}
READ_ONLY = {"rpc/dataplane/state", "rpc/cell/status", "rpc/controller/pose", "rpc/vision/info"}


class Hang(Exception):
    pass


@dataclass
class Report:
    name: str
    inputs: int = 0
    answers: int = 0  # replies that came back (not every input is answered)
    hangs: int = 0
    crashed: list[str] = field(default_factory=list)
    seconds: float = 0.0
    probe_ms: float | None = None
    in_time: bool = True
    detail: dict[str, Any] = field(default_factory=dict)
    broken: str = ""  # a promise of the target's own that did not hold (a cap not kept)

    @property
    def ok(self) -> bool:
        return not self.hangs and not self.crashed and self.in_time and not self.broken


# --- probes: one valid request per path, timed ------------------------------------------------------


class Probes:
    def __init__(self, config: CellConfig) -> None:
        self.config = config
        self.robot = config.robots[0]
        self.dp_sock = udp.open_socket(config.dataplane.sender_host)
        self.snp_sock = udp.open_socket("127.0.0.1", gro=False)
        self.rlink_sock = udp.open_socket("127.0.0.1", gro=False)
        self.hub = Topology(config.rlink).address("hub")
        self.token = 0

    def close(self) -> None:
        for s in (self.dp_sock, self.snp_sock, self.rlink_sock):
            s.close()

    def _next(self) -> int:
        self.token += 1
        return self.token

    async def skills(self, source: str = "127.0.0.2") -> None:
        """A `break` on a new connection (from another loopback address: a peer of its own)."""
        reader, writer = await asyncio.open_connection(
            self.config.skills.host, self.robot.skill_port, local_addr=(source, 0)
        )
        try:
            writer.write(Command(f"p{self._next():07d}"[-8:], "break").encode())
            reply = parse_reply((await reader.readuntil(b"\r\n"))[:-2])
            # alive: done, or stopped (the first break after a fuzzed `stop` says the motion ended early)
            stopped = isinstance(reply, Error) and reply.code == ErrorCode.STOPPED
            if not isinstance(reply, Done) and not stopped:
                raise Hang(f"break answered {reply}")
        finally:
            writer.close()

    async def dataplane(self, sock: socket.socket | None = None) -> int:
        """A status of a robot no one configured: the data plane answers it (hold)."""
        sock = sock or self.dp_sock
        seq = self._next()
        rec = datagram.empty(1)
        datagram.pack(rec, PROBE_ROBOT, 0, Kind.STATUS, seq, 0.0, 0.0)
        addr = parse_host_port(self.config.dataplane.address)
        return await _ask(sock, lambda: sock.sendto(rec.tobytes(), addr), lambda data: _has_answer(data, seq))

    async def snp(self) -> int:
        t1 = self._next()
        raw = snp.encode(snp.Header(0, snp.Pid.TSP, b"", 1, 0), snp.TimeRequest(t1))
        addr = parse_host_port(self.config.snp.listen)
        return await _ask(
            self.snp_sock, lambda: self.snp_sock.sendto(raw, addr), lambda d: _snp_time(d) == t1
        )

    async def rlink(self) -> int:
        """A NOP event for the hub, which hands it to its host's clients: back to us."""
        token = self._next().to_bytes(8, "big")
        p = rlp.Packet(rlp.Kind.EVENT, self.hub, 250, 0, rlp.EventType.NOP, 0, token)
        raw, addr = rlp.encode(p), Topology(self.config.rlink).host
        return await _ask(
            self.rlink_sock, lambda: self.rlink_sock.sendto(raw, addr), lambda d: _rlink_payload(d) == token
        )

    async def bus(self, bus: Bus) -> None:
        """A state request to the data plane, asked again after BUS_RESEND_S without its answer: a
        request sent while the server's bus connection is being made anew is lost (the bus counts the
        disconnect), which is not a hang; the caller's HANG_S bounds the whole."""
        while True:
            try:
                await bus.request(
                    "dataplane",
                    "state",
                    dataplane_pb2.StateRequest(),
                    dataplane_pb2.DataplaneState,
                    timeout=BUS_RESEND_S,
                )
                return
            except BusTimeout:
                continue
            except RemoteError as exc:
                if exc.code != FaultCode.BUS_LOST:
                    raise

    async def timed(self, probe: Callable[[], Awaitable[Any]], n: int = 5) -> list[float]:
        out = []
        for _ in range(n):
            t = time.perf_counter()
            try:
                async with asyncio.timeout(HANG_S):
                    await probe()
            except TimeoutError:
                raise Hang(f"no answer within {HANG_S:.0f} s") from None
            out.append((time.perf_counter() - t) * 1e3)
        return out


async def _ask(sock: socket.socket, send: Callable[[], Any], found: Callable[[bytes], bool]) -> int:
    """Send, and read sock until a datagram satisfies found; send again after RESEND_S without it (a
    flood of ours may have filled the peer's buffer: a lost probe is not a hang).  Returns the bytes of
    the other datagrams read meanwhile."""
    loop = asyncio.get_running_loop()
    other = 0
    while True:
        send()
        deadline = loop.time() + RESEND_S
        while loop.time() < deadline:
            try:
                data = sock.recv(65536)
            except BlockingIOError:
                ready = asyncio.Event()
                loop.add_reader(sock.fileno(), ready.set)
                try:
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout_at(deadline):
                            await ready.wait()
                finally:
                    loop.remove_reader(sock.fileno())
                continue
            if found(data):
                return other
            other += len(data)


def _has_answer(data: bytes, seq: int) -> bool:
    if len(data) % datagram.SIZE:
        return False
    recs = datagram.view(data)
    return bool(((recs["robot_id"] == PROBE_ROBOT) & (recs["seq"] == seq)).any())


def _snp_time(data: bytes) -> int | None:
    with contextlib.suppress(snp.PacketError):
        body = snp.decode(data).body
        if isinstance(body, snp.TimeResponse):
            return body.t1
    return None


def _rlink_payload(data: bytes) -> bytes | None:
    with contextlib.suppress(rlp.PacketError):
        return rlp.decode(data).payload
    return None


# --- the listeners ----------------------------------------------------------------------------------


class Listeners:
    def __init__(self, config: CellConfig, probes: Probes, inputs: int, seed: int) -> None:
        self.config, self.probes, self.n = config, probes, inputs
        self.mut = Mutator(seed)
        self.seed = seed

    def corpus(self, strategy: Any) -> list[Any]:
        return strategies.examples(strategy, SEEDS, self.seed)

    async def skills(self, rep: Report) -> None:
        """One TCP connection, every input a line (or several, or none): each line answered once."""
        corpus = self.corpus(strategies.skill_lines)
        reader, writer = await asyncio.open_connection(self.config.skills.host, self.probes.robot.skill_port)
        expected = 0
        codes: dict[str, int] = {}
        got = 0

        async def read() -> None:
            nonlocal got
            while True:
                line = await reader.readuntil(b"\r\n")
                reply = parse_reply(line[:-2])
                code = getattr(reply, "code", "done")
                codes[code] = codes.get(code, 0) + 1
                got += 1

        reading = asyncio.create_task(read())
        try:
            sent = 0
            while sent < self.n:
                chunk = []
                for _ in range(min(2000, self.n - sent)):
                    line = self.mut.line(self.mut.rng.choice(corpus), corpus)
                    events = CommandReader().feed(line)
                    if any(isinstance(e, Command) for e in events):
                        continue  # a valid command is not bad input (and could move the robot)
                    chunk.append(line)
                    expected += len(events)
                    sent += 1
                writer.write(b"".join(chunk))
                await writer.drain()
                want = expected
                await self._progress(lambda: got >= want, reading)  # noqa: B023 (awaited here)
            rep.inputs, rep.answers = sent, got
            rep.detail = {"lines_answered": got, "lines_expected": expected, "codes": codes}
        finally:
            reading.cancel()
            writer.close()

    async def _progress(self, done: Callable[[], bool], reading: asyncio.Task) -> None:
        async with asyncio.timeout(HANG_S * 4):
            while not done():
                if reading.done():
                    raise Hang(f"the reply stream ended: {reading.exception()!r}")
                await asyncio.sleep(0.002)

    async def dataplane(self, rep: Report) -> None:
        """Status records with every field odd (and robots it does not know, or does: spoofed), and
        datagrams of wrong lengths; the probe after each burst."""
        rng = np.random.default_rng(self.seed)
        corpus = self.corpus(strategies.datagrams)
        sock, addr = self.probes.dp_sock, parse_host_port(self.config.dataplane.address)
        sender = udp.Sender(sock, datagram.SIZE)
        ids = np.array([r.id for r in self.config.robots] + [0, 65535, PROBE_ROBOT, 4000], np.int64)
        wild = np.array([0, 1, -1, 2**31 - 1, -(2**31), 2**30, 12345], np.int64)
        sent = answered = 0
        while sent < self.n:
            n = min(4096, self.n - sent)
            bad = n // 20
            recs = datagram.empty(n - bad)
            m = recs.size
            recs["robot_id"] = np.where(rng.random(m) < 0.5, rng.choice(ids, m), rng.integers(0, 65536, m))
            recs["joint_id"] = np.where(rng.random(m) < 0.7, rng.integers(0, 7, m), rng.integers(0, 256, m))
            recs["kind"] = np.where(rng.random(m) < 0.8, int(Kind.STATUS), rng.integers(0, 256, m))
            recs["seq"] = rng.integers(0, 2**32, m, dtype=np.uint64)
            for f in ("velocity", "position"):
                recs[f] = np.where(rng.random(m) < 0.5, rng.choice(wild, m), rng.integers(-(2**31), 2**31, m))
            raw = recs.view(np.uint8).data
            for i in range(0, m, 64):
                sender.send(raw[i * datagram.SIZE : (i + 64) * datagram.SIZE], addr)
            for _ in range(bad):
                with contextlib.suppress(BlockingIOError):
                    sock.sendto(self.mut.havoc(self.mut.rng.choice(corpus), corpus), addr)
            sent += n
            answered += await self._probe_counting(self.probes.dataplane) // datagram.SIZE
        rep.inputs, rep.answers = sent, answered

    async def _probe_counting(self, probe: Callable[[], Awaitable[int | None]]) -> int:
        try:
            async with asyncio.timeout(HANG_S):
                return (await probe()) or 0
        except TimeoutError:
            raise Hang(f"the probe after a burst had no answer within {HANG_S:.0f} s") from None

    async def _datagrams(
        self, rep: Report, sock: socket.socket, addr: tuple[str, int], make: Callable[[], bytes], probe
    ) -> None:
        sent = 0
        while sent < self.n:
            n = min(200, self.n - sent)  # (small datagrams take ~1 KB of a receive buffer each)
            for _ in range(n):
                with contextlib.suppress(BlockingIOError):
                    sock.sendto(make(), addr)
            sent += n
            await self._probe_counting(probe)
        rep.inputs = sent

    async def snp(self, rep: Report) -> None:
        corpus = self.corpus(strategies.snp_packets)
        await self._datagrams(
            rep,
            self.probes.snp_sock,
            parse_host_port(self.config.snp.listen),
            lambda: self.mut.snp(self.mut.rng.choice(corpus), corpus),
            self.probes.snp,
        )

    async def rlink(self, rep: Report) -> None:
        corpus = self.corpus(strategies.rlink_packets)

        def make() -> bytes:
            raw = self.mut.rlink(self.mut.rng.choice(corpus), corpus)
            try:
                if rlp.decode(raw).type not in SAFE_RLINK:
                    raw = raw[:-1] + bytes([raw[-1] ^ 0xFF])  # an order or a report: its CRC broken
            except rlp.PacketError:
                pass
            return raw

        await self._datagrams(
            rep, self.probes.rlink_sock, Topology(self.config.rlink).host, make, self.probes.rlink
        )

    async def bus(self, rep: Report) -> None:
        """Frames on the services' request topics and the topics they follow, straight into the bus."""
        corpus = self.corpus(strategies.bus_frames)
        ctx = zmq.asyncio.Context.instance()
        pub, sub = ctx.socket(zmq.PUB), ctx.socket(zmq.SUB)
        enc = Encoder("fuzz", instance=0x0F0F0F0F)
        reply_topic = b"_reply/0f0f0f0f"
        pub.setsockopt(zmq.SNDHWM, 0)
        pub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.SUBSCRIBE, reply_topic)
        secure_client(pub, self.config.bus)  # (a client of this cell: forged frames, not a forged cell)
        secure_client(sub, self.config.bus)
        pub.connect(self.config.bus.pub)
        sub.connect(self.config.bus.sub)
        corr = 0

        async def probe() -> int:
            """Asked again after BUS_RESEND_S (see Probes.bus); any of its askings' answers will do."""
            nonlocal corr
            first, n = corr + 1, 0
            loop = asyncio.get_running_loop()
            while True:
                corr += 1
                pub.send(
                    enc.encode(b"rpc/dataplane/state", "cell.v1.StateRequest", b"", BusKind.REQUEST, corr)
                )
                deadline = loop.time() + BUS_RESEND_S
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout_at(deadline):
                        while True:
                            env = decode_frame(await sub.recv())
                            if first <= env.correlation <= corr:
                                return n
                            n += 1

        try:
            async with asyncio.timeout(10):  # the subscription reaches the forwarder
                while True:
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(0.2):
                            await probe()
                            break
            sent = 0
            while sent < self.n:
                n = min(1000, self.n - sent)
                for _ in range(n):
                    pub.send(_harmless(self.mut.havoc(self.mut.rng.choice(corpus), corpus)))
                sent += n
                await self._probe_counting(probe)
            rep.inputs = sent
        finally:
            pub.close()
            sub.close()

    async def ur(self, rep: Report) -> None:
        """The probe robot's UR interfaces: dashboard lines, programs, RTDE packages (cell.fuzz.ur)."""
        rep.inputs, rep.answers, rep.detail = await ur_fuzz.fuzz(
            self.probes.robot, self.config.ur, self.n, self.mut
        )

    async def config_files(self, rep: Report) -> None:
        """Config files (in this process: a config is read by whoever starts the cell): each loads or
        is refused with a ConfigError naming the key; anything else is a crash."""
        sections: dict[str, list[str]] = {}
        for name, table in load_config(None).__dict__.items():
            if hasattr(table, "__dataclass_fields__"):
                sections[name] = list(table.__dataclass_fields__)
        corpus_text = self.corpus(strategies.config_texts(sections))
        corpus = [t.encode() for t in corpus_text]
        loaded = refused = 0
        crashes: list[str] = []
        for i in range(self.n):
            text = (
                self.mut.text(self.mut.rng.choice(corpus_text), corpus) if i % 4 else corpus_text[i % SEEDS]
            )
            try:
                config_from_text(text, "fuzz.toml")
                loaded += 1
            except ConfigError:
                refused += 1
            except Exception as exc:
                if len(crashes) < 5:
                    crashes.append(f"{type(exc).__name__}: {exc} <- {text[:120]!r}")
            if i % 2000 == 0:
                await asyncio.sleep(0)
        rep.inputs, rep.answers = self.n, loaded + refused
        rep.detail = {"loaded": loaded, "refused": refused}
        rep.crashed += crashes


def _harmless(frame: bytes) -> bytes:
    """The frame, unless it is a well-formed request a service would act on or a message its
    subscribers would believe: then its envelope version is broken (it arrives malformed)."""
    try:
        env = decode_frame(frame)
    except EnvelopeError:
        return frame
    act = env.topic.startswith("rpc/") and env.topic not in READ_ONLY and env.kind == BusKind.REQUEST
    believed = False
    for prefix, cls in TRUSTING.items():
        if env.topic.startswith(prefix):
            try:
                env.decode(cls)
                believed = True
            except EnvelopeError:
                pass
    if not (act or believed):
        return frame
    at = frame.index(b"\0") + 1
    return frame[:at] + b"\x7f" + frame[at + 1 :]


# --- the attacks on resources -----------------------------------------------------------------------
