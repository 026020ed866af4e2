"""The SnP handler on UDP: the asyncio side of cell.snp.handler (which has no sockets)."""

from __future__ import annotations

import asyncio
from typing import cast

from cell.snp.handler import Address, Handler


class HandlerEndpoint(asyncio.DatagramProtocol):
    """A Handler on a UDP socket: immediate answers at once, then the queries that came in this
    wake-up, earliest deadline first."""

    def __init__(self, handler: Handler) -> None:
        self.handler = handler
        self.transport: asyncio.DatagramTransport | None = None
        self._serving = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.DatagramTransport, transport)  # (a datagram endpoint's)

    def datagram_received(self, data: bytes, addr: Address) -> None:
        for out, to in self.handler.receive(data, addr):
            self._send(out, to)
        if self.handler.pending and not self._serving:
            self._serving = True
            asyncio.get_running_loop().call_soon(self._serve)

    def _serve(self) -> None:
        """Everything that came in this wake-up is pending: answer it earliest deadline first."""
        self._serving = False
        while (out := self.handler.serve()) is not None:
            self._send(*out)

    def _send(self, data: bytes, addr: Address) -> None:
        if self.transport is not None:
            self.transport.sendto(data, addr)

    def error_received(self, exc: Exception) -> None:
        self.handler.counters.socket_errors += 1
