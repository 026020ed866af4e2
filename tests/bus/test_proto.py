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


def test_the_python_enums_are_the_protos_values() -> None:
    """cell.bus.FaultCode and cell.status.Health mirror bus.proto's FaultCode and health.proto's
    Health: a code or a health on the wire is the proto name's tail, lower-cased."""
    from cell.bus import FaultCode
    from cell.status import Health
    from cell.v1 import bus_pb2, health_pb2

    def wire(enum, prefix: str) -> set[str]:
        names = [v.name for v in enum.DESCRIPTOR.values]
        return {n.removeprefix(prefix).lower() for n in names if not n.endswith("_UNSPECIFIED")}

    assert {c.value for c in FaultCode} == wire(bus_pb2.FaultCode, "FAULT_CODE_")
    assert {h.value for h in Health} == wire(health_pb2.Health, "HEALTH_")
