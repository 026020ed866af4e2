"""The cell's child processes (layouts "groups" and "each"), supervised by the launcher.

Each child is `python -m cell service ...` in its own session, so a Ctrl-C at
the terminal reaches only the launcher, which then stops the children
(SIGTERM, then SIGKILL after a grace period).  A child whose parent dies sees
its standard input close and stops by itself: no process is left behind.
A child places itself (CPUs, real-time priority) before it starts anything.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import sys
from collections.abc import Callable
from pathlib import Path

from cell.config import CellConfig
from cell.layout import Process
from cell.supervisor import ServiceFailed

log = logging.getLogger("cell.processes")
GRACE_S = 1.5  # SIGTERM -> SIGKILL; keeps a whole shutdown inside 2 s


class ChildProcess:
    def __init__(
        self,
        process: Process,
        config: CellConfig,
        config_path: Path,
        *,
        group: bool,
        log_level: str = "INFO",
        on_restart: Callable[[str, str], None] | None = None,
    ) -> None:
        self.process = process
        self.on_restart = on_restart  # (process name, why), before each restart
        self.config = config
        self.config_path = config_path
        self.group = group  # started as `service --group NAME` (else by service names)
        self.log_level = log_level
        self.proc: asyncio.subprocess.Process | None = None
        self.starts = 0

    @property
    def name(self) -> str:
        return self.process.name

    def argv(self) -> list[str]:
        args = [sys.executable, "-m", "cell", "--log-level", self.log_level, "service"]
        args += ["--group", self.name] if self.group else self.process.services
        return [*args, "--config", str(self.config_path), "--watch-stdin"]

    async def run(self, stop: asyncio.Event) -> None:
        """Keep the child running until `stop`; restart or raise ServiceFailed when it dies."""
        policy = self.config.services
        backoff = policy.backoff_initial_s
        try:
            while not stop.is_set():
                self.proc = await asyncio.create_subprocess_exec(
                    *self.argv(), stdin=asyncio.subprocess.PIPE, start_new_session=True
                )
                self.starts += 1
                started = asyncio.get_running_loop().time()
                exited = asyncio.ensure_future(self.proc.wait())
                stopping = asyncio.ensure_future(stop.wait())
                try:
                    await asyncio.wait({exited, stopping}, return_when=asyncio.FIRST_COMPLETED)
                finally:
                    exited.cancel()
                    stopping.cancel()
                if stop.is_set():
                    break
                rc = self.proc.returncode
                what = ", ".join(self.process.services)
                log.error("process %r (%s; pid %d) exited with code %s", self.name, what, self.proc.pid, rc)
                if policy.on_failure == "stop":
                    raise ServiceFailed(self.name, f"exited with code {rc} ({what})", what="process")
                if self.on_restart is not None:
                    self.on_restart(self.name, f"process {self.name!r} exited with code {rc}")
                if asyncio.get_running_loop().time() - started > policy.backoff_max_s:
                    backoff = policy.backoff_initial_s  # it had been up a while: start over gently
                log.info("restarting %r in %.1f s", self.name, backoff)
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(backoff):
                        await stop.wait()
                backoff = min(backoff * 2, policy.backoff_max_s)
        finally:
            await self.terminate()

    async def terminate(self) -> None:
        proc = self.proc
        if proc is None or proc.returncode is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGTERM)
        try:
            async with asyncio.timeout(GRACE_S):
                await proc.wait()
        except TimeoutError:
            log.warning("process %r did not stop in %.1f s: killing it", self.name, GRACE_S)
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            await proc.wait()
        if proc.stdin is not None:
            proc.stdin.close()
