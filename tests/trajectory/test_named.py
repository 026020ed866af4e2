"""Named trajectories on disk (cell.trajectory.named): what is saved is what a restarted controller
reads, a torn or foreign file is left out with a warning, and where the state directory is."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from cell.trajectory.model import Trajectory
from cell.trajectory.named import NamedStore, state_dir


def wave(points: int, with_qd: bool) -> Trajectory:
    t = np.linspace(0.0, 2.0, points)
    q = 0.1 * np.sin(np.outer(t, np.arange(1, 7)))
    return Trajectory.build(t, q, np.gradient(q, t, axis=0) if with_qd else None)


def test_saved_trajectories_are_read_back_as_they_were(tmp_path: Path) -> None:
    store = NamedStore(tmp_path)
    kept = {1: wave(50, with_qd=True), 2: wave(7, with_qd=False)}
    store.save("pick", kept)
    store.save("place", {1: wave(3, with_qd=False)})
    store.save("pick", {2: wave(9, with_qd=True)})  # (a name given again is replaced)
    got = NamedStore(tmp_path).load_all()
    assert list(got) == ["pick", "place"] and list(got["pick"]) == [2]
    a, b = got["pick"][2], wave(9, with_qd=True)
    assert np.array_equal(a.t, b.t) and np.array_equal(a.q, b.q) and np.array_equal(a.qd, b.qd)
    assert a.qdd is None and got["place"][1].qd is None and a.name == "pick"
    assert not list((tmp_path / "named").glob(".*"))  # (no part file left behind)


def test_a_torn_or_foreign_file_is_left_out_with_a_warning(tmp_path: Path, caplog) -> None:
    store = NamedStore(tmp_path)
    store.save("good", {1: wave(5, with_qd=False)})
    (tmp_path / "named" / "torn.npz").write_bytes(b"PK\x03\x04 not a whole zip")
    np.savez(tmp_path / "named" / "foreign.npz", weights=np.zeros(3))
    (tmp_path / "named" / ".half.npz.part").write_bytes(b"PK")  # (a write the controller died in)
    with caplog.at_level(logging.WARNING, logger="cell.trajectory"):
        got = store.load_all()
    assert list(got) == ["good"]
    assert sum("not restored" in r.message for r in caplog.records) == 2


def test_where_the_state_directory_is(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CELL_STATE_DIR", str(tmp_path / "env"))
    assert state_dir("~/mine", "default") == Path.home() / "mine"  # (the configured one first)
    assert state_dir("", "default") == tmp_path / "env"
    monkeypatch.delenv("CELL_STATE_DIR")
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "xdg"))
    assert state_dir("", "lab") == tmp_path / "xdg" / "cell" / "lab"
