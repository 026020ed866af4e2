"""A cell in a child process for benchmarks: `cell up` on free ports, stopped afterwards."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import socket
import subprocess
import sys
import tempfile
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import tomli_w

from cell.bus import BusError
from cell.config import CellConfig, load_config
from cell.launcher import fetch_status


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.asynccontextmanager
async def running_cell(overrides: dict[str, Any]) -> AsyncIterator[CellConfig]:
    """`cell up` in a child process on free ports, until the block ends."""
    data = {
        "bus": {"pub": f"tcp://127.0.0.1:{free_port()}", "sub": f"tcp://127.0.0.1:{free_port()}"},
        "dataplane": {"listen": f"127.0.0.1:{free_port(socket.SOCK_DGRAM)}"},
        "snp": {"listen": f"127.0.0.1:{free_port(socket.SOCK_DGRAM)}"},
        **overrides,
    }
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.toml"
        path.write_text(tomli_w.dumps(data))
        config = load_config(path)
        proc = await asyncio.create_subprocess_exec(
            *[sys.executable, "-m", "cell", "--log-level", "WARNING", "up", "--config", str(path)],
            stdin=subprocess.DEVNULL,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        try:
            want = set(config.services.run)
            async with asyncio.timeout(30):
                while True:
                    try:
                        st = await fetch_status(config, timeout=1.0)
                        if want <= {s.name for s in st.services if s.health == "ok"}:
                            break
                    except BusError:
                        pass
                    await asyncio.sleep(0.1)
            yield config
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                async with asyncio.timeout(10):
                    await proc.wait()
            except TimeoutError:
                proc.kill()
                await proc.wait()
