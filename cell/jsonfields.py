"""Results as typed dataclasses that print as JSON (a bench's figures, an experiment's summary): the
fields are the JSON keys, so the type and the machine-readable line cannot drift apart."""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any, Protocol, cast

# a field's metadata: its key is left out of to_json() while it is None (a step that did not run)
OMIT_IF_NONE = {"json": "omit if None"}


class Result(Protocol):
    """Typed figures; to_json() is their JSON object (a bench's `--json` line, its --results section)."""

    def to_json(self) -> dict[str, Any]: ...


class JsonFields:
    """A result dataclass whose fields are its JSON keys (nested dataclasses as objects, in order);
    a field marked OMIT_IF_NONE appears only once it holds something."""

    def to_json(self) -> dict[str, Any]:
        out = dataclasses.asdict(cast(Any, self))  # (a mixin of dataclasses)
        for f in dataclasses.fields(cast(Any, self)):
            if f.metadata == OMIT_IF_NONE and out[f.name] is None:
                del out[f.name]
        return out


def finite(value: Any) -> Any:
    """value with every NaN or infinity in it as None (null): JSON has no NaN, and a strict reader
    (jq, JavaScript's JSON.parse, Go's encoding/json) refuses the `NaN` Python's json writes."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite(v) for v in value]
    return value


def json_line(value: Any) -> str:
    """One line of strict JSON (a figure that could not be measured, NaN, is null)."""
    return json.dumps(finite(value), allow_nan=False)
