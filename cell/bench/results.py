"""The benches' figures in one generated page (docs/results.md): each bench run with `--results FILE`
replaces its own section, so the page holds every bench's latest figures with the command and the
date that produced them, and no prose that goes stale."""

from __future__ import annotations

import datetime
import platform
import re
from pathlib import Path
from typing import Any

HEADER = """# Measured figures

Generated: each section is written by the bench it names, run with `--results docs/results.md`
(its other options as shown). Figures are from this project's development machine (2 cores, a VM
that stalls now and then); compare ratios within one run, not absolute figures across runs.
How each bench measures: [performance.md](performance.md).
"""


def _rows(result: dict[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    """The figures as (key, value) rows: numbers and short strings, nested tables flattened one level."""
    rows = []
    for key, value in result.items():
        name = f"{prefix}{key}"
        if isinstance(value, bool) or value is None:
            rows.append((name, str(value).lower()))
        elif isinstance(value, int | float):
            rows.append((name, f"{value:.4g}" if isinstance(value, float) else str(value)))
        elif isinstance(value, str) and len(value) <= 80:
            rows.append((name, value))
        elif isinstance(value, dict) and not prefix:
            rows += _rows(value, f"{name}.")
    return rows


def section(bench: str, argv: list[str], result: dict[str, Any]) -> str:
    when = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    lines = [
        f"## {bench}",
        "",
        f"`cell {' '.join(argv)}`, {when}, {platform.node() or 'this host'} "
        f"(Python {platform.python_version()})",
        "",
        "| figure | value |",
        "|---|---|",
        *(f"| `{k}` | {v} |" for k, v in _rows(result)),
        "",
    ]
    return "\n".join(lines)


def write(path: str | Path, bench: str, argv: list[str], result: dict[str, Any]) -> None:
    """Replace (or add) the bench's section of the page, keeping the others in name order."""
    path = Path(path)
    text = path.read_text() if path.exists() else HEADER
    head, *parts = re.split(r"(?m)^(?=## )", text)
    sections = {p.split("\n", 1)[0][3:].strip(): p.rstrip() + "\n" for p in parts}
    sections[bench] = section(bench, argv, result)
    body = "\n".join(sections[k] for k in sorted(sections))
    path.write_text(head.rstrip() + "\n\n" + body)
