"""The bus forwarder: pyzmq's steerable XSUB/XPUB proxy, run in a thread.

The proxy loop is libzmq's own (C, GIL released), so forwarding costs no
Python time; we only steer it (STATISTICS, TERMINATE) over an inproc REQ/REP.
Its XSUB subscribes to everything so that every publisher sends every message
from the moment it is connected (the node's sync ping relies on this; see
cell/bus/node.py), and filtering happens once, at the XPUB.
"""

from __future__ import annotations

import itertools
import struct
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING

import zmq

import cell.bus.curve as curve
import cell.bus.identity as identity
from cell.bus.node import BusError, readable, secure_server, tune, zmq_context
from cell.config import BusConfig

if TYPE_CHECKING:
    from zmq.auth.thread import ThreadAuthenticator

_ids = itertools.count()


@dataclass(frozen=True, slots=True)
class ForwarderStats:
    """libzmq's proxy statistics; it counts frames, and a bus message is one frame."""

    frames_in: int
    bytes_in: int
    frames_out: int
    bytes_out: int
    subscription_msgs: int

    def as_counters(self) -> dict[str, float]:
        return {
            "forwarder.messages_in": self.frames_in,
            "forwarder.bytes_in": self.bytes_in,
            "forwarder.messages_out": self.frames_out,
            "forwarder.bytes_out": self.bytes_out,
            "forwarder.subscription_msgs": self.subscription_msgs,
        }


class Forwarder:
    def __init__(self, config: BusConfig) -> None:
        self.config = config
        self._thread: threading.Thread | None = None
        self._control_ep = f"inproc://cell-forwarder-{next(_ids)}"
        self._ctl: zmq.Socket | None = None
        self._auth: ThreadAuthenticator | None = None
        self.guard: identity.Guard | None = None

    def start(self) -> None:
        """Bind both endpoints (BusError if taken) and start forwarding."""
        ctx = zmq_context()
        # the guard comes first: no connection gets in before it (the allow-list of keys, or the
        # cell's identity: cell/bus/identity.py)
        if self.config.curve:
            self._auth = curve.start_authenticator(ctx, self.config)
        else:
            self.guard = identity.Guard.register(ctx, self.config.cell, identity.member_token())
        xsub, xpub, rep = ctx.socket(zmq.XSUB), ctx.socket(zmq.XPUB), ctx.socket(zmq.REP)
        self._sockets = (xsub, xpub, rep)
        for sock in self._sockets:
            sock.setsockopt(zmq.LINGER, 0)
        for sock in (xsub, xpub):
            secure_server(sock, self.config)
            tune(sock, self.config)
        try:
            xsub.bind(self.config.pub)
            xpub.bind(self.config.sub)
        except zmq.ZMQError as exc:
            self._close_sockets()
            raise BusError(
                f"bus forwarder cannot bind {self.config.pub} / {self.config.sub}: {exc}"
            ) from None
        rep.bind(self._control_ep)
        xsub.send(b"\x01")  # subscribe to everything upstream: publishers send all from the start
        # sockets move to the proxy thread here; thread start is the memory barrier ZeroMQ asks for
        self._thread = threading.Thread(
            target=zmq.proxy_steerable, args=(xsub, xpub, None, rep), name="cell-forwarder", daemon=True
        )
        self._thread.start()
        self._ctl = zmq_context().socket(zmq.REQ)
        self._ctl.setsockopt(zmq.LINGER, 0)
        self._ctl.connect(self._control_ep)

    def counters(self) -> dict[str, float]:
        """What the guard refused (connections of another cell, or of another start of this one)."""
        return self.guard.counters() if self.guard is not None else {}

    async def statistics(self) -> ForwarderStats:
        assert self._ctl is not None, "start() first"
        self._ctl.send(b"STATISTICS")
        await readable(self._ctl)
        raw = self._ctl.recv_multipart()
        v = [struct.unpack("=Q", f)[0] for f in raw]
        # frontend (XSUB) in / bytes in / out / bytes out, then the same for the backend (XPUB)
        return ForwarderStats(v[0], v[1], v[6], v[7], v[4])

    def stop(self, timeout: float = 1.0) -> None:
        """Stop the proxy thread and close every socket; safe to call twice."""
        if self._thread is None:
            return
        ctl = zmq_context().socket(zmq.REQ)
        ctl.setsockopt(zmq.LINGER, 0)
        ctl.setsockopt(zmq.RCVTIMEO, int(timeout * 1000))
        ctl.connect(self._control_ep)
        try:
            ctl.send(b"TERMINATE")
            ctl.recv()
        except zmq.Again:
            pass
        finally:
            ctl.close(linger=0)
        self._thread.join(timeout)
        if self._thread.is_alive():
            raise BusError("bus forwarder thread did not stop")
        self._thread = None
        if self._ctl is not None:
            self._ctl.close(linger=0)
            self._ctl = None
        self._close_sockets()

    def _close_sockets(self) -> None:
        for sock in self._sockets:
            if not sock.closed:
                sock.close(linger=0)
        if self._auth is not None:
            self._auth.stop()
            self._auth = None
        if self.guard is not None:
            self.guard.release()
            self.guard = None
