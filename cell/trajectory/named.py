"""Named trajectories kept on disk, so that they outlive the controller that took them.

One file a name, `<state dir>/named/<name>.npz`: each robot's times, positions and (if given)
velocities and accelerations under `r<id>_t`, `r<id>_q`, `r<id>_qd`, `r<id>_qdd`.  A file is
written beside its place and renamed onto it, so a controller killed mid-write leaves the old file
or the new one, never half of one; a file that cannot be read is reported and skipped, never fatal.

The state directory is `[controller] state_dir`, else `$CELL_STATE_DIR`, else
`$XDG_STATE_HOME/cell/<cell name>` (`~/.local/state/cell/<cell name>`).
"""

from __future__ import annotations

import logging
import os
import re
import zipfile
from pathlib import Path

import numpy as np

from cell.trajectory.model import Trajectory, TrajectoryError

log = logging.getLogger("cell.trajectory")
_KEY = re.compile(r"^r(\d+)_(t|q|qd|qdd)$")


def state_dir(configured: str, cell_name: str) -> Path:
    """Where the cell keeps what must outlive its processes."""
    if configured:
        return Path(configured).expanduser()
    if env := os.environ.get("CELL_STATE_DIR"):
        return Path(env)
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "cell" / cell_name


class NamedStore:
    """The named trajectories' files in one directory."""

    def __init__(self, root: Path) -> None:
        self.root = root / "named"

    def _path(self, name: str) -> Path:
        return self.root / f"{name}.npz"

    def save(self, name: str, trajectories: dict[int, Trajectory]) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        arrays: dict[str, np.ndarray] = {}
        for rid, tr in trajectories.items():
            arrays[f"r{rid}_t"], arrays[f"r{rid}_q"] = tr.t, tr.q
            if tr.qd is not None:
                arrays[f"r{rid}_qd"] = tr.qd
            if tr.qdd is not None:
                arrays[f"r{rid}_qdd"] = tr.qdd
        part = self.root / f".{name}.npz.part"
        with part.open("wb") as f:
            np.savez(f, **arrays)  # type: ignore[arg-type]  # (numpy's stub misreads **kwds)
            f.flush()
            os.fsync(f.fileno())
        part.replace(self._path(name))

    def load_all(self) -> dict[str, dict[int, Trajectory]]:
        """Every name kept, in name order; files that cannot be read are logged and left out."""
        out: dict[str, dict[int, Trajectory]] = {}
        if not self.root.is_dir():
            return out
        for path in sorted(self.root.glob("*.npz")):
            try:
                out[path.stem] = self._read(path)
            except (OSError, ValueError, KeyError, zipfile.BadZipFile, TrajectoryError) as exc:
                log.warning("named trajectory %s not restored: %s", path, exc)
        return out

    def _read(self, path: Path) -> dict[int, Trajectory]:
        with np.load(path, allow_pickle=False) as z:
            parts: dict[int, dict[str, np.ndarray]] = {}
            for key in z.files:
                m = _KEY.match(key)
                if m is None:
                    raise ValueError(f"an entry {key!r} no trajectory file has")
                parts.setdefault(int(m[1]), {})[m[2]] = z[key]
        if not parts:
            raise ValueError("no trajectories in it")
        return {
            rid: Trajectory.build(p["t"], p["q"], p.get("qd"), p.get("qdd"), name=path.stem)
            for rid, p in parts.items()
        }
