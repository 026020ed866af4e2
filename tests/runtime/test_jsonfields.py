"""Typed results print as the JSON their fields name; a field marked OMIT_IF_NONE only once it is set."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import pytest

from cell.jsonfields import OMIT_IF_NONE, JsonFields, json_line


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


def test_a_json_line_is_strict_json_a_figure_not_measured_null() -> None:
    """A bench's t_upd with no table update is NaN: its line says null, which every reader takes."""
    line = json_line({"t_upd_ms": math.nan, "p": [math.inf, 1.5], "cpu": {"x": -math.inf, "n": 3}})
    assert line == '{"t_upd_ms": null, "p": [null, 1.5], "cpu": {"x": null, "n": 3}}'
    json.loads(line, parse_constant=lambda c: pytest.fail(f"not strict JSON: {c}"))
