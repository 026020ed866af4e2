"""Typed results print as the JSON their fields name; a field marked OMIT_IF_NONE only once it is set."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

from cell.jsonfields import OMIT_IF_NONE, JsonFields


@dataclass
class Inner(JsonFields):
    p99: float


@dataclass
class Outer(JsonFields):
    n: int
    rtt: Inner
    per_target: dict[str, Inner]
    nothing: float | None  # a null the line keeps
    extra: Inner | None = field(default=None, metadata=OMIT_IF_NONE)


def test_fields_are_the_keys_in_order_nested_and_a_marked_none_is_left_out() -> None:
    r = Outer(3, Inner(1.5), {"xdp": Inner(2.0)}, None)
    assert json.dumps(r.to_json()) == (
        '{"n": 3, "rtt": {"p99": 1.5}, "per_target": {"xdp": {"p99": 2.0}}, "nothing": null}'
    )
    r.extra = Inner(0.25)
    assert list(r.to_json()) == ["n", "rtt", "per_target", "nothing", "extra"]
    assert r.to_json()["extra"] == {"p99": 0.25}
