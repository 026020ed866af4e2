"""The bus over real ZeroMQ sockets through a real forwarder."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace

import pytest
import zmq

from cell.bus import (
    Bus,
    BusError,
    BusTimeout,
    BusUnavailable,
    FaultCode,
    Forwarder,
    RemoteError,
    RpcFault,
    ServiceDown,
    node,
)
from cell.bus.envelope import Encoder
from cell.bus.node import secure_client, zmq_context
from cell.config import BusConfig
from cell.v1 import bus_pb2, health_pb2
from tests.conftest import cell_env, free_port


def payload(i: int) -> bus_pb2.BenchPayload:
    return bus_pb2.BenchPayload(data=i.to_bytes(4, "big"))


async def collect(sub, n: int, timeout: float = 5.0) -> list:
    got: list = []
    async with asyncio.timeout(timeout):
        while len(got) < n:
            got += await sub.recv_batch()
    return got


async def test_publish_subscribe_round_trip(forwarder: BusConfig) -> None:
    async with Bus.connect(forwarder, "pub") as pub, Bus.connect(forwarder, "sub") as sub_node:
        sub = await sub_node.subscribe("status/")
        pub.publish("status/r1", payload(1))
        env = await sub.recv(timeout=5)
        assert env.topic == "status/r1"
        assert env.source == "pub"
        assert env.instance == pub.instance
        assert env.type_name == "cell.v1.BenchPayload"
        assert env.message() == payload(1)
        assert 0 < time.monotonic_ns() - env.sent_ns < 5e9


async def test_prefix_filtering(forwarder: BusConfig) -> None:
    async with Bus.connect(forwarder, "pub") as pub, Bus.connect(forwarder, "sub") as node:
        sub = await node.subscribe("a/", "c/")
        for topic in ("b/x", "a/x", "ab/x", "c/y", "b/z"):
            pub.publish(topic, payload(0))
        pub.publish("c/end", payload(0))
        got = await collect(sub, 3)
        assert [e.topic for e in got] == ["a/x", "c/y", "c/end"]


@pytest.mark.parametrize("attempt", range(10))
async def test_no_lost_first_messages_from_a_new_publisher(forwarder: BusConfig, attempt: int) -> None:
    """The slow-joiner case: a publisher publishes the moment connect() returns."""
    async with Bus.connect(forwarder, "sub") as node:
        sub = await node.subscribe("first/")
        async with Bus.connect(forwarder, f"new-{attempt}") as pub:
            for i in range(50):
                pub.publish("first/x", payload(i))
        got = await collect(sub, 50)
        assert [e.decode(bus_pb2.BenchPayload).data for e in got] == [payload(i).data for i in range(50)]
        assert [e.seq for e in got] == list(range(50))
        assert sub.lost == 0


async def test_no_lost_first_messages_to_a_new_subscription(forwarder: BusConfig) -> None:
    """Whatever is published after subscribe() returns is delivered."""
    async with Bus.connect(forwarder, "pub") as pub, Bus.connect(forwarder, "sub") as node:
        for round_ in range(10):
            sub = await node.subscribe(f"late{round_}/")
            pub.publish(f"late{round_}/x", payload(round_))
            assert (await sub.recv(timeout=5)).message() == payload(round_)
            sub.close()
        assert node.counters()["bus.received"] == 10  # closed subscriptions still count


def raw_publisher(cfg: BusConfig) -> zmq.Socket:
    sock = zmq_context().socket(zmq.PUB)
    sock.setsockopt(zmq.LINGER, 0)
    secure_client(sock, cfg)  # (the cell's identity: else the forwarder refuses it)
    sock.connect(cfg.pub)
    return sock


async def send_until_seen(sock: zmq.Socket, sub, frame: bytes) -> None:
    """Raw sockets have no sync handshake: repeat a marker until it arrives, then the path is live."""
    async with asyncio.timeout(5):
        while True:
            sock.send(frame)
            try:
                await sub.recv(timeout=0.02)
                return
            except TimeoutError:
                continue


async def test_gaps_and_malformed_messages_are_counted(forwarder: BusConfig) -> None:
    async with Bus.connect(forwarder, "sub") as node:
        sub = await node.subscribe("g/")
        sock = raw_publisher(forwarder)
        try:
            enc = Encoder("raw")
            await send_until_seen(sock, sub, enc.encode(b"g/marker", "cell.v1.Empty", b""))
            sub.gaps.lost = 0  # counting starts now (the marker repeats do not matter)
            for i in range(10):
                frame = enc.encode(b"g/x", "cell.v1.BenchPayload", payload(i).SerializeToString())
                if i not in (3, 4, 7):  # lose three on purpose
                    sock.send(frame)
            for junk in (b"g/bad", b"g/bad\0short", b"g/bad\0" + b"\x09" * 40):
                sock.send(junk)
            sock.send_multipart([b"g/two", b"frames"])  # each frame arrives alone, and is junk
            sock.send(enc.encode(b"g/end", "cell.v1.Empty", b""))
            got = await collect(sub, 8)
        finally:
            sock.close()
        assert [e.topic for e in got][-1] == "g/end"
        assert [e.decode(bus_pb2.BenchPayload).data for e in got[:-1]] == [
            payload(i).data for i in range(10) if i not in (3, 4, 7)
        ]
        assert sub.lost == 3
        assert sub.malformed == 5


async def test_request_reply_and_errors(forwarder: BusConfig) -> None:
    async def double(req: bus_pb2.BenchPayload) -> bus_pb2.BenchPayload:
        await asyncio.sleep(0)
        return bus_pb2.BenchPayload(data=req.data * 2)

    def full(_req: bus_pb2.Empty) -> bus_pb2.Empty:
        raise RpcFault(FaultCode.REFUSED, "table full (50000 of 50000)")

    def broken(_req: bus_pb2.Empty) -> bus_pb2.Empty:
        raise ZeroDivisionError("oops")

    methods = {
        "double": (bus_pb2.BenchPayload, double),
        "full": (bus_pb2.Empty, full),
        "broken": (bus_pb2.Empty, broken),
    }
    async with Bus.connect(forwarder, "server") as server, Bus.connect(forwarder, "client") as client:
        await server.serve("svc", methods)
        reply = await client.request("svc", "double", bus_pb2.BenchPayload(data=b"ab"), bus_pb2.BenchPayload)
        assert reply.data == b"abab"

        cases = [  # (each code one of FaultCode's, as the wire carries it: its string)
            ("full", bus_pb2.Empty(), FaultCode.REFUSED, "table full"),
            ("broken", bus_pb2.Empty(), FaultCode.INTERNAL, "ZeroDivisionError: oops"),
            ("nothing", bus_pb2.Empty(), FaultCode.UNKNOWN_METHOD, "svc/nothing"),
            ("double", bus_pb2.Empty(), FaultCode.BAD_REQUEST, "expected a cell.v1.BenchPayload"),
        ]
        for method, msg, code, text in cases:
            with pytest.raises(RemoteError) as info:
                await client.request("svc", method, msg)
            assert (info.value.service, info.value.method, info.value.code) == ("svc", method, code)
            assert FaultCode(info.value.code) is code
            assert text in info.value.message
        # the server survived every failure
        reply = await client.request("svc", "double", bus_pb2.BenchPayload(data=b"z"), bus_pb2.BenchPayload)
        assert reply.data == b"zz"
        assert server.served == 6


async def test_concurrent_requests_are_matched_by_correlation_id(forwarder: BusConfig) -> None:
    async def slow_echo(req: bus_pb2.BenchPayload) -> bus_pb2.BenchPayload:
        # later requests answer first, so replies come back out of order
        await asyncio.sleep((50 - int.from_bytes(req.data, "big")) * 0.001)
        return req

    async with Bus.connect(forwarder, "server") as server, Bus.connect(forwarder, "client") as client:
        await server.serve("svc", {"echo": (bus_pb2.BenchPayload, slow_echo)})
        replies = await asyncio.gather(
            *(client.request("svc", "echo", payload(i), bus_pb2.BenchPayload) for i in range(50))
        )
        assert [r.data for r in replies] == [payload(i).data for i in range(50)]


async def test_request_without_server_times_out_clearly(forwarder: BusConfig) -> None:
    async with Bus.connect(forwarder, "client") as client:
        t0 = time.monotonic()
        with pytest.raises(BusTimeout, match=r"no reply from nobody\.hello within 0\.3 s"):
            await client.request("nobody", "hello", bus_pb2.Empty(), timeout=0.3)
        assert 0.3 <= time.monotonic() - t0 < 1.0
        assert isinstance(BusTimeout("x"), TimeoutError)


async def test_late_reply_is_counted_not_delivered(forwarder: BusConfig) -> None:
    release = asyncio.Event()

    async def stall(req: bus_pb2.Empty) -> bus_pb2.Empty:
        await release.wait()
        return req

    async with Bus.connect(forwarder, "server") as server, Bus.connect(forwarder, "client") as client:
        await server.serve("svc", {"stall": (bus_pb2.Empty, stall)})
        with pytest.raises(BusTimeout):
            await client.request("svc", "stall", bus_pb2.Empty(), timeout=0.1)
        release.set()
        served = server.served
        async with asyncio.timeout(5):
            while client.late_replies == 0:
                await client.request(
                    "svc", "stall", bus_pb2.Empty()
                )  # a fresh round trip flushes the late one
        assert server.served > served
        assert client.late_replies == 1


async def test_a_reply_that_came_while_the_requesters_loop_was_held_is_not_a_timeout(
    forwarder: BusConfig,
) -> None:
    """A requester whose own loop is held past the deadline (a controller busy with a fleet) gets the
    reply that reached it in time, not a BusTimeout: its timers are not the server's silence."""
    up, stop = threading.Event(), threading.Event()

    def server() -> None:
        async def main() -> None:
            async with Bus.connect(forwarder, "server") as srv:
                await srv.serve("svc", {"echo": (bus_pb2.BenchPayload, lambda req: req)})
                up.set()
                while not stop.is_set():
                    await asyncio.sleep(0.01)

        asyncio.run(main())

    thread = threading.Thread(target=server, daemon=True)
    thread.start()
    try:
        assert await asyncio.to_thread(up.wait, 10)
        async with Bus.connect(forwarder, "client") as client:
            await client.request("svc", "echo", payload(0), bus_pb2.BenchPayload)  # (the path is up)
            asked = asyncio.create_task(client.request("svc", "echo", payload(7), bus_pb2.BenchPayload, 0.2))
            await asyncio.sleep(0)  # (the request is sent, its timer set)
            # this loop held (the fault) past the deadline, until the reply has come in meanwhile
            held_until = time.monotonic() + 0.3
            while time.monotonic() < held_until:
                time.sleep(0.01)  # noqa: ASYNC251  (holding this loop is the point)
            assert client._ctl.poll(10_000, zmq.POLLIN), "the server never answered"
            reply = await asked
            assert reply.data == payload(7).data
            assert client.late_replies == 0
    finally:
        stop.set()
        thread.join(10)


async def test_no_forwarder_is_a_clear_error(bus_config: BusConfig) -> None:
    cfg = replace(bus_config, connect_timeout_s=0.3)
    t0 = time.monotonic()
    with pytest.raises(BusUnavailable, match="no bus forwarder answered"):
        async with Bus.connect(cfg, "lonely"):
            pass
    assert time.monotonic() - t0 < 1.5


async def test_node_exceptions_propagate_unwrapped(forwarder: BusConfig) -> None:
    with pytest.raises(KeyError):
        async with Bus.connect(forwarder, "n"):
            raise KeyError("mine")


async def test_forwarder_statistics_count_messages(forwarder: BusConfig) -> None:
    own = replace(forwarder, pub=f"tcp://127.0.0.1:{free_port()}", sub=f"tcp://127.0.0.1:{free_port()}")
    fwd = Forwarder(own)
    fwd.start()
    try:
        before = await fwd.statistics()
        async with Bus.connect(own, "a") as a:
            sub = await a.subscribe("s/")
            for i in range(20):
                a.publish("s/x", payload(i))
            await collect(sub, 20)
        after = await fwd.statistics()
        # 20 messages plus the sync pings of connect() and subscribe()
        assert 20 < after.frames_in - before.frames_in < 40
        assert 20 < after.frames_out - before.frames_out < 40
        assert after.bytes_in - before.bytes_in > 20 * len(payload(0).SerializeToString())
        assert after.as_counters()["forwarder.messages_in"] == after.frames_in
    finally:
        fwd.stop()


def test_forwarder_refuses_a_taken_port(forwarder: BusConfig) -> None:
    with pytest.raises(BusError, match="cannot bind"):
        Forwarder(forwarder).start()


async def test_two_readers_on_one_subscription_is_an_error(forwarder: BusConfig) -> None:
    async with Bus.connect(forwarder, "n") as node:
        sub = await node.subscribe("only/")
        first = asyncio.create_task(sub.recv())
        await asyncio.sleep(0)  # one loop pass: the task runs up to its first await (deterministic)
        with pytest.raises(RuntimeError, match="already waiting"):
            await sub.recv()
        node.publish("only/x", payload(1))
        assert (await asyncio.wait_for(first, 5)).message() == payload(1)  # the first reader still works


async def test_junk_on_a_served_topic_is_counted_and_the_server_still_answers(forwarder: BusConfig) -> None:
    def echo(req: bus_pb2.BenchPayload) -> bus_pb2.BenchPayload:
        return req

    async with Bus.connect(forwarder, "server") as server, Bus.connect(forwarder, "client") as client:
        await server.serve("svc", {"echo": (bus_pb2.BenchPayload, echo)})
        sock = raw_publisher(forwarder)
        try:
            # raw sockets have no handshake: send junk until the server has counted some
            async with asyncio.timeout(5):
                while server.malformed < 3:
                    for junk in (
                        b"rpc/svc/echo",
                        b"rpc/svc/echo\0\x01\x01",
                        b"rpc/svc/echo\0" + b"\xff" * 60,
                    ):
                        sock.send(junk)
                    await asyncio.sleep(0.01)  # let the server's reader run between bursts
        finally:
            sock.close()
        reply = await client.request("svc", "echo", payload(5), bus_pb2.BenchPayload)
        assert reply == payload(5)
        assert server.served == 1  # junk was never mistaken for a request


async def test_a_patient_node_starts_without_a_forwarder_and_joins_when_one_comes(
    bus_config: BusConfig,
) -> None:
    cfg = replace(bus_config, connect_timeout_s=0.2)
    t0 = time.monotonic()
    async with Bus.connect(cfg, "early", wait=False) as early:
        assert time.monotonic() - t0 < 0.2  # yielded at once: the service serves its own sockets
        early.publish("x/lost", payload(0))  # into the void: never an error
        serving = asyncio.ensure_future(early.serve("svc", {"echo": (bus_pb2.BenchPayload, lambda r: r)}))
        await asyncio.sleep(0.5)  # past connect_timeout_s: a patient node keeps waiting
        assert not serving.done()
        fwd = Forwarder(cfg)
        fwd.start()
        try:
            async with asyncio.timeout(5):
                await serving
            async with Bus.connect(cfg, "client") as client:
                assert await client.request("svc", "echo", payload(3), bus_pb2.BenchPayload) == payload(3)
        finally:
            fwd.stop()


async def test_abandon_answers_waiting_requests_at_once(forwarder: BusConfig) -> None:
    async with Bus.connect(forwarder, "client") as client:
        waiting = [
            asyncio.ensure_future(client.request("gone", "move", payload(i), timeout=30)) for i in range(2)
        ]
        other = asyncio.ensure_future(client.request("other", "x", payload(9), timeout=30))
        await asyncio.sleep(0)  # (the requests are on their way)
        assert client.abandon("gone", "stopped", "the service died") == 2
        for w in waiting:
            with pytest.raises(RemoteError) as info:
                await w
            assert (info.value.code, info.value.message, info.value.method) == (
                "stopped",
                "the service died",
                "move",
            )
        assert not other.done()  # only the dead service's requests
        other.cancel()


async def test_a_request_to_a_service_said_failed_by_its_supervisor_is_answered(forwarder: BusConfig) -> None:
    """A service that dies mid-request under a supervisor: the supervisor's event on the bus answers
    what waits on it now (not at its timeout, which may be a whole motion long), saying why."""
    Event = health_pb2.ServiceEvent

    def event(service: str, kind: int, text: str = "") -> Event:
        return Event(service=service, kind=kind, text=text, restarts=1)

    async with Bus.connect(forwarder, "client") as client, Bus.connect(forwarder, "supervisor") as sup:
        moving = asyncio.ensure_future(client.request("modular", "move", payload(1), timeout=30))
        other = asyncio.ensure_future(client.request("vision", "measure", payload(2), timeout=30))
        await asyncio.sleep(0)  # (the requests are on their way)
        t0 = time.monotonic()
        died = "RuntimeError: the cycle's routers process ended; restart 1 in 0.5 s"
        sup.publish("events/service/modular", event("modular", Event.KIND_RESTARTING, died))
        with pytest.raises(ServiceDown) as info:  # (a BusTimeout: no reply, done or not; known now)
            await moving
        assert (info.value.service, info.value.method, info.value.why) == ("modular", "move", died)
        assert isinstance(info.value, BusTimeout) and died in str(info.value)
        assert time.monotonic() - t0 < 5.0 and not other.done()  # (only the failed service's)
        # junk on the events' topic is counted, nothing else; a request timing out says the service is down
        sup.publish("events/service/vision", payload(3))
        sup.publish("events/service/vision", event("vision", Event.KIND_FAILED, "OSError: camera gone"))
        with pytest.raises(ServiceDown, match="camera gone"):
            await other
        assert client.malformed == 1
        with pytest.raises(BusTimeout, match=r"service 'modular' is down: RuntimeError: the cycle's routers"):
            await client.request("modular", "move", payload(4), timeout=0.3)
        # back: its start clears it (the next event, from the same publisher, comes after it)
        sup.publish("events/service/modular", event("modular", Event.KIND_STARTED))
        waiting = asyncio.ensure_future(client.request("vision", "measure", payload(5), timeout=30))
        await asyncio.sleep(0)
        sup.publish("events/service/vision", event("vision", Event.KIND_RESTARTING, "again"))
        with pytest.raises(ServiceDown, match="again"):
            await waiting
        with pytest.raises(BusTimeout, match=r"is service 'modular' running\?"):
            await client.request("modular", "move", payload(6), timeout=0.3)


async def test_requests_waiting_when_the_forwarder_dies_are_answered_at_once(bus_config: BusConfig) -> None:
    fwd = Forwarder(bus_config)
    fwd.start()
    release = asyncio.Event()

    async def slow(req: bus_pb2.BenchPayload) -> bus_pb2.BenchPayload:
        await release.wait()
        return req

    try:
        async with Bus.connect(bus_config, "server") as server, Bus.connect(bus_config, "client") as client:
            await server.serve("svc", {"slow": (bus_pb2.BenchPayload, slow)})
            waiting = asyncio.ensure_future(client.request("svc", "slow", payload(1), timeout=30))
            async with asyncio.timeout(5):
                while server.requests == 0 and not server._handlers:  # (the request has reached it)
                    await asyncio.sleep(0.01)
            t0 = time.monotonic()
            fwd.stop()
            with pytest.raises(RemoteError) as info:
                await waiting
            assert info.value.code == "bus_lost" and time.monotonic() - t0 < 2.0
            assert client.counters()["bus.disconnects"] >= 1
            release.set()
    finally:
        fwd.stop()


async def test_a_subscriber_wakes_though_its_fd_number_was_left_registered_by_a_closed_file(
    forwarder: BusConfig,
) -> None:
    """ZeroMQ closes a socket's FD in its own thread; the number comes back for a new socket while
    the event loop may still hold the old registration.  Then asyncio would only update its map,
    never tell epoll about the new file, and the subscriber would sleep on a full queue."""
    loop = asyncio.get_running_loop()
    async with Bus.connect(forwarder, "pub") as pub, Bus.connect(forwarder, "sub") as sub_bus:
        r, w = os.pipe()
        os.close(w)
        loop.add_reader(r, lambda: None)  # registered, then closed behind the loop's back ...
        os.close(r)
        stale = node.wakeups["stale"]
        sub = await sub_bus.subscribe("t/")  # ... and its number taken by the new socket's FD
        if sub._sock.getsockopt(zmq.FD) != r:
            loop.remove_reader(r)
            pytest.skip("the subscription's FD did not take the closed file's number")
        got = asyncio.ensure_future(sub.recv(timeout=node.RECHECK_S / 2))  # the FD must wake it
        await asyncio.sleep(0)  # (it is waiting now)
        pub.publish("t/x", bus_pb2.BenchPayload(data=b"wake"))
        env = await got
    assert env.decode(bus_pb2.BenchPayload).data == b"wake" and node.wakeups["stale"] == stale + 1


async def test_a_subscriber_whose_wake_up_edge_was_consumed_still_gets_its_message(
    forwarder: BusConfig,
) -> None:
    """ZeroMQ's FD is edge-like: whoever reads EVENTS first takes the edge.  Taken behind the waiter's
    back, the waiter still looks at EVENTS every RECHECK_S and is counted as a missed wake-up."""
    async with Bus.connect(forwarder, "pub") as pub, Bus.connect(forwarder, "sub") as sub_bus:
        sub = await sub_bus.subscribe("t/")
        missed = node.wakeups["missed"]
        got = asyncio.ensure_future(sub.recv(timeout=5 * node.RECHECK_S))
        await asyncio.sleep(0)  # (it is waiting on the FD now)
        pub.publish("t/x", bus_pb2.BenchPayload(data=b"edge"))
        deadline = time.monotonic() + 2
        while not sub._sock.getsockopt(zmq.EVENTS) & zmq.POLLIN:  # (this read takes the edge)
            assert time.monotonic() < deadline
            time.sleep(0.001)  # noqa: ASYNC251 (the event loop must not run: it would take the edge itself)
        env = await got
    assert env.decode(bus_pb2.BenchPayload).data == b"edge" and node.wakeups["missed"] == missed + 1


async def test_a_hung_forwarder_is_noticed_by_heartbeats_and_the_bus_works_once_it_is_back(
    bus_config: BusConfig,
) -> None:
    """A peer that hangs keeps its TCP connections open; only ZMTP heartbeats notice (and get a
    connection out of a stream stalled behind a shut receive window).  The forwarder runs in a child
    process here, so that SIGSTOP hangs it and nothing else."""
    cfg = replace(bus_config, heartbeat_s=0.1, heartbeat_timeout_s=0.3)
    code = (
        "import sys, time; from cell.bus import Forwarder; from cell.config import load_config\n"
        "from dataclasses import replace\n"
        f"fwd = Forwarder(replace(load_config(None).bus, pub={cfg.pub!r}, sub={cfg.sub!r},"
        " heartbeat_s=0.1, heartbeat_timeout_s=0.3)); fwd.start(); print('up', flush=True)\n"
        "sys.stdin.read()\n"
    )
    child = subprocess.Popen(
        [sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=cell_env()
    )
    try:
        assert child.stdout is not None and child.stdout.readline() == "up\n"
        async with Bus.connect(cfg, "node") as bus, Bus.connect(cfg, "server") as server:
            await server.serve("svc", {"echo": (bus_pb2.BenchPayload, lambda r: r)})
            sub = await bus.subscribe("hb/")
            os.kill(child.pid, signal.SIGSTOP)
            try:
                async with asyncio.timeout(5):  # heartbeat_timeout_s after the last PONG
                    while bus.counters()["bus.disconnects"] == 0:
                        await asyncio.sleep(0.05)
            finally:
                os.kill(child.pid, signal.SIGCONT)
            # the server's own connection came back too: it proves its path by asking itself (its
            # subscriptions are re-sent on reconnection ahead of its ping).  A request sent before the
            # server is back is lost (the forwarder has no subscriber for it yet): seen on this VM in
            # every run for an afternoon, the server back ~0.1 s after the requester
            back = await server.request("svc", "echo", payload(9), bus_pb2.BenchPayload, timeout=5)
            assert back == payload(9)
            # at once: a request is not lost in the requester's reconnection (it proves the path first)
            assert await bus.request("svc", "echo", payload(8), bus_pb2.BenchPayload, timeout=5) == payload(8)
            async with asyncio.timeout(5):  # subscriptions were sent anew: messages flow
                while True:
                    bus.publish("hb/x", payload(7))
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(0.2):
                            got = await sub.recv_batch()
                            assert got[0].decode(bus_pb2.BenchPayload) == payload(7)
                            break
    finally:
        child.kill()
        child.wait()
