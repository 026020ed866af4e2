"""A bus link with latency and jitter, for trying a controller that sits far away (edge cloud, VM).

DelayLink binds its own pub/sub endpoints and forwards everything, both ways,
to and from a real bus, each message `delay` +/- `jitter` seconds late
(uniform), never overtaking the one before it, as on a TCP connection.
Nodes that connect to its endpoints see the whole bus through a slow link.
`tc netem` would do this in the kernel; it is not available everywhere
(not on this project's CI machines), so it is done here in user space.

Loss is loss on a TCP connection, which the bus runs on: a lost segment is
sent again after the retransmission timeout (Linux's minimum, 200 ms), and
everything behind it waits (head-of-line blocking); nothing is lost for good.
delay, jitter and loss may be changed while the link runs (a fault campaign).
"""

from __future__ import annotations

import asyncio
import random
import time
from collections import deque
from dataclasses import replace

import zmq

import cell.bus.identity as identity
from cell.bus.node import readable, secure_client, secure_server, tune, zmq_context
from cell.config import BusConfig


class DelayLink:
    def __init__(
        self,
        bus: BusConfig,
        pub: str,
        sub: str,
        delay: float,
        jitter: float,
        seed: int = 0,
        loss: float = 0.0,
        rto: float = 0.2,
    ) -> None:
        if jitter > delay:
            raise ValueError("jitter must not exceed the delay")
        if not 0.0 <= loss < 1.0:
            raise ValueError("loss must be in [0, 1)")
        self.bus, self.delay, self.jitter = bus, delay, jitter
        self.loss, self.rto = loss, rto
        self.retransmitted = 0
        self.config = replace(bus, pub=pub, sub=sub)  # what nodes behind the link connect with
        self._rng = random.Random(seed)
        self.forwarded = 0

    async def run(self) -> None:
        """Forward until cancelled."""
        ctx = zmq_context()
        up_in = ctx.socket(zmq.XSUB)  # the far nodes publish here ...
        up_out = ctx.socket(zmq.PUB)  # ... and it goes on into the bus
        down_in = ctx.socket(zmq.SUB)  # everything from the bus ...
        down_out = ctx.socket(zmq.XPUB)  # ... out to the far nodes' subscriptions
        socks = (up_in, up_out, down_in, down_out)
        # (its far side asks the far nodes who they are, as the forwarder would, with a guard of its
        # own where the forwarder is elsewhere: it lets in the nodes of this cell's name; the forwarder
        # sees the link itself, a client)
        guard = None if self.bus.curve else identity.Guard.register(ctx, self.bus.cell, "")
        try:
            for s in socks:
                tune(s, self.bus)
            for s in (up_in, down_out):  # (the far nodes shake hands with the link as with the bus)
                secure_server(s, self.bus)
            for s in (up_out, down_in):
                secure_client(s, self.bus)
            up_in.bind(self.config.pub)
            up_in.send(b"\x01")  # subscribe to everything the far publishers send
            up_out.connect(self.bus.pub)
            down_in.connect(self.bus.sub)
            down_in.subscribe(b"")
            down_out.bind(self.config.sub)
            async with asyncio.TaskGroup() as tg:
                tg.create_task(self._pipe(up_in, up_out))
                tg.create_task(self._pipe(down_in, down_out))
                tg.create_task(self._drain(down_out))
        finally:
            for s in socks:
                s.close()
            if guard is not None:
                guard.release()

    async def _drain(self, xpub: zmq.Socket) -> None:
        """Subscription messages from the far side: XPUB filters by them itself; read them away."""
        while True:
            await readable(xpub)
            while True:
                try:
                    xpub.recv(zmq.NOBLOCK)
                except zmq.Again:
                    break

    async def _pipe(self, src: zmq.Socket, dst: zmq.Socket) -> None:
        queue: deque[tuple[float, list[bytes]]] = deque()
        wake = asyncio.Event()
        last_due = 0.0

        async def sender() -> None:
            while True:
                if not queue:
                    wake.clear()
                    await wake.wait()
                    continue
                due, frames = queue[0]
                wait = due - time.monotonic()
                if wait > 0:
                    await asyncio.sleep(wait)
                queue.popleft()
                dst.send_multipart(frames)
                self.forwarded += 1

        async with asyncio.TaskGroup() as tg:
            tg.create_task(sender())
            while True:
                await readable(src)
                while True:
                    try:
                        frames = src.recv_multipart(zmq.NOBLOCK)
                    except zmq.Again:
                        break
                    now = time.monotonic()
                    due = now + self.delay + self._rng.uniform(-self.jitter, self.jitter)
                    if self.loss and self._rng.random() < self.loss:
                        due += self.rto  # lost once, sent again after the retransmission timeout
                        self.retransmitted += 1
                    last_due = max(due, last_due)  # no overtaking
                    queue.append((last_due, frames))
                    wake.set()
