"""CurveZMQ on the bus: every connection encrypted, and only allow-listed clients let in.

`cell keys generate` writes, into [bus] keys (a directory):

    server.key, server.key_secret      the forwarder's certificate (the secret stays on its host)
    <client>.key, <client>.key_secret  one certificate per client name (a host, a team, a tool)
    allowed/<client>.key               the allow-list: the public keys the forwarder accepts

Each host gets server.key and its own client's pair; the forwarder's host also
gets server.key_secret and allowed/.  pyzmq's ZAP authenticator
(zmq.auth.thread.ThreadAuthenticator) runs beside the forwarder and refuses
any client whose public key is not in allowed/; a refused node learns it from
its socket monitor (EVENT_HANDSHAKE_FAILED_*), and connecting fails with a
message that says so.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from cell.config import BusConfig

SERVER = "server"
ALLOWED = "allowed"


class KeysMissing(Exception):
    """Keys missing or unreadable: says which file and what to run."""


def generate(directory: str | Path, clients: list[str]) -> list[Path]:
    """Create the server certificate (if absent) and one per client, allow-listing each; the files
    written.  Existing certificates are kept: generating again only adds clients."""
    d = Path(directory)
    allowed = d / ALLOWED
    allowed.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for name in [SERVER, *clients]:
        public, secret = d / f"{name}.key", d / f"{name}.key_secret"
        if not (public.exists() and secret.exists()):
            public_s, secret_s = zmq.auth.create_certificates(d, name)
            os.chmod(secret_s, 0o600)
            written += [Path(public_s), Path(secret_s)]
        if name != SERVER:
            shutil.copy(public, allowed / public.name)
            written.append(allowed / public.name)
    return written


def _load(path: Path, secret: bool) -> tuple[bytes, bytes | None]:
    try:
        public, sec = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as exc:
        raise KeysMissing(f"{path}: {exc} (run `cell keys generate --dir {path.parent}`)") from None
    if secret and sec is None:
        raise KeysMissing(f"{path}: no secret key in it (the .key_secret file is needed here)")
    return public, sec


def secure_server(sock: zmq.Socket, cfg: BusConfig) -> None:
    """Make a forwarder socket a CURVE server with the cell's server certificate."""
    public, secret = _load(Path(cfg.keys) / f"{SERVER}.key_secret", secret=True)
    sock.curve_secretkey = secret
    sock.curve_publickey = public
    sock.curve_server = True


def secure_client(sock: zmq.Socket, cfg: BusConfig) -> None:
    """Make a node's socket a CURVE client with this host's client certificate."""
    public, secret = _load(Path(cfg.keys) / f"{cfg.client}.key_secret", secret=True)
    server, _ = _load(Path(cfg.keys) / f"{SERVER}.key", secret=False)
    sock.curve_secretkey = secret
    sock.curve_publickey = public
    sock.curve_serverkey = server


def start_authenticator(ctx: zmq.Context, cfg: BusConfig) -> ThreadAuthenticator:
    """The ZAP handler that lets in only the clients in keys/allowed/."""
    allowed = Path(cfg.keys) / ALLOWED
    if not allowed.is_dir():
        raise KeysMissing(f"{allowed}: no allow-list (run `cell keys generate --dir {cfg.keys}`)")
    auth = ThreadAuthenticator(ctx)
    auth.start()
    auth.configure_curve(domain="*", location=str(allowed))
    return auth
