"""The live web viewer at the address the cell prints, in a real browser (Debian's headless Chromium).

`make test` installs Chromium where root and apt allow; without it this is skipped with the reason.
The viewer draws on a WebGL canvas, so its page has no text to read.  What is checked is what the
viewer does with the printed address: it opens the cell's recording (a connection from the browser
to the loopback gRPC proxy, which the bare address, Rerun's welcome page, never makes), and the page
it draws is not the welcome page.  The browser is driven over the DevTools protocol.
"""

from __future__ import annotations

import asyncio
import base64
import itertools
import json
import logging
import shutil
import subprocess
import urllib.request
from pathlib import Path

import pytest

from tests.conftest import free_port

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None, reason="no chromium (make test installs Debian's where root and apt allow)"
)
# headless, nothing but loopback, WebGL in software (the viewer renders with SwiftShader here)
FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
    "--disable-sync", "--window-size=1280,800",
]  # fmt: skip


def _peers(port: int) -> int:
    """Established TCP connections to 127.0.0.1:port (counted at the listening end)."""
    n = 0
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        f = line.split()
        if f[3] == "01" and int(f[1].split(":")[1], 16) == port:  # 01: ESTABLISHED
            n += 1
    return n


class Browser:
    """Headless Chromium and one page of it, over the DevTools protocol."""

    def __init__(self, profile: Path) -> None:
        port = free_port()
        cmd = [
            CHROMIUM,
            *FLAGS,
            f"--user-data-dir={profile}",
            f"--remote-debugging-port={port}",
            "about:blank",
        ]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.port, self.ids = port, itertools.count(1)
        self.events: list[str] = []  # (the DevTools events heard, by name)

    async def __aenter__(self) -> Browser:
        import websockets

        async with asyncio.timeout(30):
            while True:
                try:
                    pages = await asyncio.to_thread(self._pages)
                    break
                except OSError:
                    await asyncio.sleep(0.1)  # (until the browser listens)
        self.ws = await websockets.connect(pages[0]["webSocketDebuggerUrl"], max_size=None)
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.ws.close()
        self.proc.kill()
        self.proc.wait()

    def _pages(self) -> list[dict]:
        with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/json/list", timeout=1) as r:
            return [t for t in json.load(r) if t["type"] == "page"]

    async def call(self, method: str, **params: object) -> dict:
        n = next(self.ids)
        await self.ws.send(json.dumps({"id": n, "method": method, "params": params}))
        while True:
            msg = json.loads(await self.ws.recv())
            if msg.get("id") == n:
                assert "error" not in msg, msg
                return msg["result"]
            self.events.append(msg.get("method", ""))

    async def open(self, url: str) -> None:
        """Navigate, until the page has loaded."""
        await self.call("Page.enable")
        self.events = []
        await self.call("Page.navigate", url=url)
        async with asyncio.timeout(30):
            while "Page.loadEventFired" not in self.events:
                self.events.append(json.loads(await self.ws.recv()).get("method", ""))

    async def screenshot(self) -> bytes:
        return base64.b64decode((await self.call("Page.captureScreenshot", format="png"))["data"])

    async def settled(self, timeout: float = 60.0) -> bytes:
        """The page's screenshot once two taken 1 s apart are the same (it has finished drawing)."""
        last = b""
        async with asyncio.timeout(timeout):
            while True:
                shot = await self.screenshot()
                if shot == last:
                    return shot
                last = shot
                await asyncio.sleep(1.0)  # (the interval between two looks at the page)


@pytest.mark.slow
async def test_the_printed_address_opens_the_cells_recording_in_a_browser(
    tmp_path: Path, caplog, monkeypatch
) -> None:
    import rerun as rr

    from cell.recorder import serve
    from cell.recorder.live import open_recording

    grpc_port, web_port = free_port(), free_port()
    monkeypatch.setattr(serve, "GRPC_PORT", grpc_port)  # (what open_recording serves on)
    monkeypatch.setattr(serve, "WEB_PORT", web_port)
    with caplog.at_level(logging.INFO, logger="cell.service.recorder"):
        rec = open_recording("serve", "", "viewer-test")
    try:
        printed = next(r.getMessage() for r in caplog.records if "web viewer" in r.getMessage())
        url = printed.rsplit(" ", 1)[1]
        assert url.startswith(f"http://127.0.0.1:{web_port}/?url=") and f"{grpc_port}" in url
        rec.log("world/robots/r1/tool", rr.Points3D([[0.3, 0.1, 0.4]], radii=0.02))
        rec.log("world/robots/r1/links", rr.LineStrips3D([[[0, 0, 0], [0, 0, 0.16], [0.3, 0.1, 0.4]]]))
        rec.flush()
        ours = _peers(grpc_port)  # (the recording's own stream to the proxy)
        async with Browser(tmp_path / "profile") as page:
            await page.open(f"http://127.0.0.1:{web_port}/")
            welcome = await page.settled()
            assert _peers(grpc_port) == ours  # the bare address opens nothing: Rerun's welcome page
            await page.open(url)
            async with asyncio.timeout(60):
                while _peers(grpc_port) <= ours:  # (until the viewer has opened the recording)
                    await asyncio.sleep(0.05)
            view = await page.settled()
        (tmp_path / "view.png").write_bytes(view)
        assert view != welcome, "the printed address drew Rerun's welcome page"
    finally:
        serve.close(rec)
