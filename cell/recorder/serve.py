"""`--rerun serve` on loopback only: the web viewer and its gRPC endpoint, bound to 127.0.0.1.

The SDK's own serve calls (`serve_grpc`, `serve_web_viewer`) listen on every
interface and take no bind address, which would put a live view of the cell
on the network.  The `rerun` CLI takes `--bind`, so the cell runs it as a
child process bound to 127.0.0.1 and streams the recording to it over gRPC.
Reach it from elsewhere through an SSH tunnel, or use `save` / `spawn`.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # (this module is imported by `cell up` to check its ports: no SDK for that)
    import rerun as rr

HOST = "127.0.0.1"
GRPC_PORT, WEB_PORT = 9876, 9090
_servers: dict[int, subprocess.Popen] = {}  # id(recording) -> its server


class ServeError(RuntimeError):
    """The loopback viewer could not be started: said with what to do instead."""


def rerun_binary() -> str:
    """The viewer's own executable: the `rerun` command of rerun-sdk is a Python wrapper that runs it as
    a child, and waiting on (or stopping) the wrapper alone would leave the server listening."""
    with contextlib.suppress(ImportError):
        import rerun_cli

        exe = Path(rerun_cli.__file__).parent / "rerun"
        if exe.exists():
            return str(exe)
    found = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
    if not Path(found).exists():
        raise ServeError("no `rerun` command next to this Python: use --rerun save PATH.rrd or spawn")
    return found


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex((HOST, port)) == 0


def taken(grpc_port: int | None = None, web_port: int | None = None) -> str | None:
    """Why the loopback viewer cannot start (one of its ports taken: what to do instead), or None.
    `cell up --rerun serve` asks before anything starts."""
    for port in (GRPC_PORT if grpc_port is None else grpc_port, WEB_PORT if web_port is None else web_port):
        if _listening(port):
            return f"{HOST}:{port} is taken (another viewer?): stop it, or use --rerun save PATH.rrd or spawn"
    return None


# runs the viewer with the kernel's promise to SIGTERM it when the process that started it ends,
# however that ends (SIGKILL too): prctl(PR_SET_PDEATHSIG) before exec, in a child of its own (a
# preexec_fn in a process with threads may deadlock); none started if that parent is gone already
_DIE_WITH_PARENT = (
    "import ctypes, os, signal, sys\n"
    "ctypes.CDLL(None).prctl(1, signal.SIGTERM, 0, 0, 0)\n"
    "os.getppid() == int(sys.argv[1]) or sys.exit(1)\n"
    "os.execv(sys.argv[2], sys.argv[2:])\n"
)


def serve(rec: rr.RecordingStream, grpc_port: int | None = None, web_port: int | None = None) -> str:
    """Start the loopback viewer server and stream `rec` to it; the web address that opens the viewer
    on this recording (the bare address opens Rerun's welcome page).  Ports: GRPC_PORT, WEB_PORT.
    The server ends with this process, whatever ends it (it is a child that the kernel stops then)."""
    grpc_port = GRPC_PORT if grpc_port is None else grpc_port
    web_port = WEB_PORT if web_port is None else web_port
    if why := taken(grpc_port, web_port):
        raise ServeError(why)
    cmd = [
        sys.executable, "-c", _DIE_WITH_PARENT, str(os.getpid()),
        rerun_binary(), "--serve-web", "--bind", HOST, "--port", str(grpc_port),
        "--web-viewer-port", str(web_port),
    ]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    deadline = time.monotonic() + 20
    while not (_listening(grpc_port) and _listening(web_port)):
        if proc.poll() is not None or time.monotonic() > deadline:
            _stop(proc)
            err = (proc.stderr.read() if proc.stderr else b"").decode(errors="replace")[-500:]
            raise ServeError(f"the loopback viewer did not start ({err.strip() or 'no output'})")
        time.sleep(0.05)
    rec.connect_grpc(f"rerun+http://{HOST}:{grpc_port}/proxy")
    _servers[id(rec)] = proc
    return f"http://{HOST}:{web_port}/?url=rerun%2Bhttp%3A%2F%2F{HOST}%3A{grpc_port}%2Fproxy"


def close(rec: rr.RecordingStream) -> None:
    """Flush and disconnect the recording, and stop its loopback server if it has one."""
    with contextlib.suppress(Exception):
        rec.flush()
    rec.disconnect()
    proc = _servers.pop(id(rec), None)
    if proc is not None:
        _stop(proc)


def _stop(proc: subprocess.Popen) -> None:
    """The server and what it started (the `rerun` command may be a wrapper around the viewer): its
    whole process group, which is its own (start_new_session)."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(5)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
