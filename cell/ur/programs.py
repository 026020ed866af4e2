"""An arm's programs folder, as URSim's /ursim/programs: where the dashboard's `load` and
`load installation` find .urp and .installation files, and where `saveLog`, `generate flight report`
and `generate support file` write theirs.  Paths a client names are resolved inside it: a name that
leads out of it (`..`, an absolute path elsewhere) is not found, so a dashboard client can read and
write nothing else on the host."""

from __future__ import annotations

import io
import json
import os
import time
import zipfile
from pathlib import Path

from cell.ur.arm import DATAGRAM_PROGRAM

DEFAULT_INSTALLATION = "default.installation"


def default_folder() -> Path:
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "cell" / "programs"


class Programs:
    """The folder (made on first use with the cell's own program and a default installation in it,
    as a fresh URSim has its own)."""

    def __init__(self, folder: str = "") -> None:
        self.root = (Path(folder).expanduser() if folder else default_folder()).resolve()

    def ensure(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        for name, text in (
            (DATAGRAM_PROGRAM, "the cell's datagram program: the data plane's commands drive the arm\n"),
            (DEFAULT_INSTALLATION, "the cell's default installation\n"),
        ):
            f = self.root / name
            if not f.exists():
                f.write_text(text)

    def _inside(self, name: str) -> Path | None:
        """`name` (relative to the folder, or an absolute path) resolved, if it lies in the folder;
        None for one outside it, or one no file system takes (a NUL byte, too long a name)."""
        try:
            path = Path(name)
            path = (path if path.is_absolute() else self.root / path).resolve()
        except (ValueError, OSError):
            return None
        return path if path.is_relative_to(self.root) else None

    def find(self, name: str, suffix: str) -> Path | None:
        """The file `name` if it is in the folder and ends in `suffix`; else None."""
        path = self._inside(name) if name else None
        try:
            return path if path is not None and path.suffix == suffix and path.is_file() else None
        except OSError:
            return None

    def directory(self, name: str) -> Path | None:
        path = self._inside(name or ".")
        try:
            return path if path is not None and path.is_dir() else None
        except OSError:
            return None

    def save_log(self, lines: list[str]) -> Path:
        self.ensure()
        path = self.root / "log_history.txt"
        with path.open("a") as f:
            f.writelines(f"{line}\n" for line in lines)
        return path

    def flight_report(self, kind: str, state: dict[str, object]) -> str:
        """A report of the arm's state now, under flight_reports/; its id."""
        self.ensure()
        report_id = time.strftime("%Y%m%d%H%M%S") + f"{time.time_ns() % 1_000_000:06d}"
        folder = self.root / "flight_reports"
        folder.mkdir(exist_ok=True)
        body = {"id": report_id, "type": kind or "system", "time": time.time(), "state": state}
        (folder / f"flight_report_{report_id}.json").write_text(json.dumps(body, indent=1))
        return report_id

    def support_file(self, into: Path, state: dict[str, object], log: list[str]) -> Path:
        """A zip of the arm's state and its log, into `into` (a directory of the folder)."""
        path = into / f"ur_support_file_{time.strftime('%Y-%m-%d_%H-%M-%S')}.zip"
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
            z.writestr("state.json", json.dumps(state, indent=1))
            z.writestr("log_history.txt", "".join(f"{line}\n" for line in log))
        path.write_bytes(buf.getvalue())
        return path
