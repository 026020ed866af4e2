"""The committed generated code in cell/v1 matches what the pinned protoc makes of proto/."""

from __future__ import annotations

from pathlib import Path

from cell import protogen


def test_generated_code_is_fresh(tmp_path: Path) -> None:
    fresh = {p.name: p.read_bytes() for p in protogen.generate(tmp_path)}
    committed_dir = protogen.ROOT / "cell" / "v1"
    committed = {p.name: p.read_bytes() for p in committed_dir.glob("*_pb2.py*")}
    assert fresh, "protoc produced nothing"
    stale = sorted(n for n in fresh.keys() | committed.keys() if fresh.get(n) != committed.get(n))
    assert not stale, f"cell/v1 is stale for {stale}: run `make proto` and commit the result"
