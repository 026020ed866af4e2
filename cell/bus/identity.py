"""The cell's identity on its bus: no node joins a bus whose cell is not its own.

Every bus connection shakes hands with ZeroMQ's PLAIN mechanism (without CurveZMQ; with it, the
allow-list of keys is what lets a node in): the user name is the cell's name ([cell] name) and the
password the start it belongs to, a random token the `cell up` that runs the forwarder makes and
hands its processes (and the launchers of the cell's other hosts, in CellStatus.member) in the
environment variable CELL_MEMBER.  The forwarder's ZAP handler (Guard) lets in:

- a node of this cell's name with this start's token: a member;
- a node of this cell's name with no token: a client (`cell status`, `cell run`, a test, a tool);

and refuses, at the handshake and before a byte of it is forwarded, a node of another cell's name,
or one carrying another start's token (a service of a second `cell up`, or one left running by a
start that died): counted (`forwarder.refused`), logged once per kind of refusal.  The refused node
learns it from its socket monitor and stops trying (cell.bus.node: BusRefused).

This is identity, not security: the token travels in clear on the loopback or the plant's network.
"""

from __future__ import annotations

import contextlib
import logging
import os
import secrets
import threading

import zmq

log = logging.getLogger("cell.bus")

MEMBER_ENV = "CELL_MEMBER"
ZAP_ENDPOINT = "inproc://zeromq.zap.01"  # (libzmq's fixed address of a context's ZAP handler)
CLIENT = b"-"  # the password of a node with no start of its own


def member_token() -> str:
    """The start this process belongs to ("" if none: a client)."""
    return os.environ.get(MEMBER_ENV, "")


def join(token: str) -> None:
    """Make this process (and the processes it starts from now on) a member of that start."""
    os.environ[MEMBER_ENV] = token


def new_start() -> str:
    """A new start of the cell, of which this process is a member: its token."""
    token = secrets.token_hex(8)
    join(token)
    return token


def identify(sock: zmq.Socket, cell: str) -> None:
    """Make a node's socket say which cell (and start) it belongs to, in its handshake."""
    sock.plain_username = cell.encode()
    sock.plain_password = member_token().encode() or CLIENT


def serve_identity(sock: zmq.Socket, cell: str) -> None:
    """Make a forwarder's socket ask its nodes who they are (the Guard answers, for `cell`)."""
    sock.zap_domain = cell.encode()
    sock.plain_server = True


class Guard:
    """A context's ZAP handler: who may join the bus of each cell whose forwarder runs here (one
    per context; forwarders register their cell, its token, and their sockets ask under the cell's
    name as their ZAP domain).  See the module's docstring."""

    _lock = threading.Lock()
    _of: dict[int, Guard] = {}  # id(context) -> its guard

    @classmethod
    def register(cls, ctx: zmq.Context, cell: str, token: str) -> Guard:
        with cls._lock:
            guard = cls._of.get(id(ctx))
            if guard is None:
                guard = cls._of[id(ctx)] = cls(ctx)
            if token or cell.encode() not in guard.cells:  # (a start's token is never loosened)
                guard.cells[cell.encode()] = token.encode()
            guard.users += 1
            return guard

    def release(self) -> None:
        with self._lock:
            self.users -= 1
            if self.users:
                return
            self._of.pop(self._ctx_id, None)
        self._stop.set()
        self._thread.join(1.0)

    def __init__(self, ctx: zmq.Context) -> None:
        self.cells: dict[bytes, bytes] = {}  # cell name -> the token of its start ("": any)
        self.users = 0
        self.refused = 0  # connections refused
        self.last_refusal = ""
        self._said: set[str] = set()
        self._ctx_id = id(ctx)
        self._sock = ctx.socket(zmq.REP)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.bind(ZAP_ENDPOINT)  # (before any socket of the context takes a connection)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="cell-bus-guard", daemon=True)
        self._thread.start()

    def verdict(self, domain: bytes, mechanism: bytes, credentials: list[bytes]) -> str:
        """Why a node with these credentials may not join the bus of cell `domain` ("" if it may)."""
        cell = domain.decode(errors="replace")
        if mechanism != b"PLAIN" or len(credentials) != 2:
            return f"it gave no cell identity (mechanism {mechanism.decode(errors='replace')})"
        user, password = credentials
        if user != domain:
            return f"it belongs to cell {user.decode(errors='replace')!r}, this bus to {cell!r}"
        token = self.cells.get(domain, b"")
        if token and password not in (CLIENT, token):
            return f"it belongs to another start of cell {cell!r} (not this cell up's)"
        return ""

    def _serve(self) -> None:
        poller = zmq.Poller()
        poller.register(self._sock, zmq.POLLIN)
        try:
            while not self._stop.is_set():
                if not poller.poll(100):
                    continue
                frames = self._sock.recv_multipart()
                if len(frames) < 6:  # (not a ZAP request; REP needs an answer all the same)
                    self._sock.send_multipart([b"1.0", b"", b"500", b"bad request", b"", b""])
                    continue
                version, request_id, domain, address, _routing, mechanism, *credentials = frames
                why = self.verdict(domain, mechanism, credentials)
                if why:
                    self.refused += 1
                    peer = address.decode(errors="replace")
                    self.last_refusal = f"a node at {peer}: {why}"
                    if why not in self._said:  # (it retries every reconnect interval: said once)
                        self._said.add(why)
                        log.warning("bus: refused a node at %s: %s", peer, why)
                code, text = (b"400", why.encode()[:255]) if why else (b"200", b"OK")
                self._sock.send_multipart([version, request_id, code, text, b"", b""])
        except zmq.ZMQError:
            pass  # (the context is going)
        finally:
            # unbound first: a close lets go of an inproc name only when ZeroMQ's reaper gets to it, and
            # the next forwarder of this process (a restart, a test) binds the name again at once
            with contextlib.suppress(zmq.ZMQError):
                self._sock.unbind(ZAP_ENDPOINT)
            self._sock.close(linger=0)

    def counters(self) -> dict[str, float]:
        return {"forwarder.refused": self.refused}
