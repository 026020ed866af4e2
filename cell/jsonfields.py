"""Results as typed dataclasses that print as JSON (a bench's figures, an experiment's summary): the
fields are the JSON keys, so the type and the machine-readable line cannot drift apart."""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol, cast


class Result(Protocol):
    """Typed figures; to_json() is their JSON object (a bench's `--json` line, its --results section)."""

    def to_json(self) -> dict[str, Any]: ...


class JsonFields:
    """A result dataclass whose fields are its JSON keys (nested dataclasses as objects, in order)."""

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(cast(Any, self))  # (a mixin of dataclasses)
