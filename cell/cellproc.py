"""A cell in a child process for benchmarks and campaigns: `cell up` on free ports, stopped afterwards."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import tempfile
from collections.abc import AsyncIterator
from dataclasses import asdict
from pathlib import Path
from typing import Any

import tomli_w

from cell.config import CellConfig, load_config
from cell.launcher import child_cell
from cell.ports import free_block, free_port
from cell.rlink.cellnet import PORTS
from cell.status import Health


def default_robots() -> list[dict[str, Any]]:
    """The default cell's [[robots]], each on a skill port free now (a campaign's cell beside a
    running one)."""
    return [{**asdict(r), "skill_port": free_port()} for r in load_config(None).robots]


def ok_services(st: Any) -> set[str]:
    """The services a CellStatus says are ok."""
    return {s.name for s in st.services if s.health == Health.OK}


@contextlib.asynccontextmanager
async def running_cell(overrides: dict[str, Any], quiet: bool = False) -> AsyncIterator[CellConfig]:
    """`cell up` in a child process on free ports, until the block ends (quiet: without its summary)."""
    data = {
        "bus": {"pub": f"tcp://127.0.0.1:{free_port()}", "sub": f"tcp://127.0.0.1:{free_port()}"},
        "dataplane": {"listen": f"127.0.0.1:{free_port(socket.SOCK_DGRAM)}"},
        "snp": {"listen": f"127.0.0.1:{free_port(socket.SOCK_DGRAM)}"},
        "rlink": {"port": free_block(PORTS)},
        **overrides,
    }
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.toml"
        path.write_text(tomli_w.dumps(data))
        config = load_config(path)
        async with child_cell(path, config, quiet):
            yield config


async def robots_heard(ctl: Any, ids: set[int], timeout: float = 15.0) -> None:
    """Until the data plane has had a status from each of these robots (ctl: a Controller)."""
    async with asyncio.timeout(timeout):
        while {r.robot_id for r in (await ctl.link.state()).robots if r.status_ns} < ids:  # noqa: ASYNC110
            await asyncio.sleep(0.05)
