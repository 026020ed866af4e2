"""Counters that code reads, as slotted dataclasses: `c.queries += 1` is checked (a misspelt name is an
AttributeError, not a new key that reads 0 elsewhere), and as_dict() flattens them into the flat
name -> number map a heartbeat carries (see health.proto), names unchanged.

A count keyed by what a peer sent (why a packet was refused, why a query was denied) is a Tally
field: its keys come from the codec's own names, not from the counting site, and flatten as
"<field>.<key>" (or as bare keys, for a Tally declared with tally(prefix=""))."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any


def tally(prefix: str | None = None, keys: tuple[str, ...] = ()) -> Any:
    """A Tally field: counts by key, keys known up front shown as 0; flattened under
    prefix ("<field name>." when None)."""
    return field(default_factory=lambda: dict.fromkeys(keys, 0), metadata={"prefix": prefix})


@dataclass(slots=True)
class Counters:
    """Base of every counters dataclass: int and float fields are counters or gauges, dict fields
    are tallies (see tally())."""

    def as_dict(self, prefix: str = "") -> dict[str, float]:
        out: dict[str, float] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, dict):
                sub = f.metadata.get("prefix")
                sub = f"{f.name}." if sub is None else sub
                out.update({f"{prefix}{sub}{k}": v for k, v in value.items()})
            elif isinstance(value, int | float):
                out[prefix + f.name] = value
        return out

    def count(self, tally_name: str, key: str, n: int = 1) -> None:
        """Add n to one key of a tally field (the field's name is checked, the key is the peer's)."""
        t = getattr(self, tally_name)
        t[key] = t.get(key, 0) + n
