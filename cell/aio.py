"""Event-loop plumbing: uvloop where available, and stop-on-signal."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import sys
from collections.abc import Coroutine, Iterator
from typing import Any, TypeVar

T = TypeVar("T")
log = logging.getLogger("cell")
_shutting_down = False


def begin_shutdown() -> None:
    """This process is stopping on purpose (its supervisor was told to): what then goes away (the bus,
    a peer) is the shutdown, not a fault, and is not logged as one."""
    global _shutting_down
    _shutting_down = True


def shutting_down() -> bool:
    return _shutting_down


def run(coro: Coroutine[Any, Any, T]) -> T:
    """asyncio.run on uvloop when it is installed (several times faster on sockets)."""
    try:
        import uvloop
    except ImportError:
        factory = None
    else:
        factory = uvloop.new_event_loop
    with asyncio.Runner(loop_factory=factory) as runner:
        return runner.run(coro)


@contextlib.contextmanager
def stop_on_signals(stop: asyncio.Event) -> Iterator[None]:
    """SIGINT/SIGTERM set `stop` for an orderly shutdown; a second one exits at once."""
    loop = asyncio.get_running_loop()

    def handler(signum: int) -> None:
        if stop.is_set():
            log.warning("second %s: exiting now", signal.Signals(signum).name)
            os._exit(128 + signum)
        log.info("%s: shutting down", signal.Signals(signum).name)
        stop.set()

    sigs = (signal.SIGINT, signal.SIGTERM)
    for sig in sigs:
        loop.add_signal_handler(sig, handler, sig)
    try:
        yield
    finally:
        for sig in sigs:
            loop.remove_signal_handler(sig)


async def stop_on_stdin_eof(stop: asyncio.Event) -> asyncio.BaseTransport:
    """Set `stop` when standard input closes: a child's way to notice that its parent died."""

    class _Watch(asyncio.Protocol):
        def connection_lost(self, exc: Exception | None) -> None:
            stop.set()

        def eof_received(self) -> bool:
            stop.set()
            return False

    transport, _ = await asyncio.get_running_loop().connect_read_pipe(_Watch, sys.stdin)
    return transport
