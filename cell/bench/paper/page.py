"""The page of `cell bench paper`: each experiment's Section (our numbers beside the paper's, our
plot), the machine it ran on, and the HTML they are written as."""

from __future__ import annotations

import datetime
import html
import json
import os
import platform
import subprocess
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

Log = Callable[[str], None]


@dataclass
class Section:
    """One figure of the paper: our plot and the numbers side by side."""

    key: str
    title: str
    paper_ref: str
    rows: list[tuple[str, str, str]] = field(default_factory=list)  # (what, the paper's, ours)
    png: str | None = None
    notes: str = ""
    figures: dict[str, Any] = field(default_factory=dict)  # ours, machine-readable
    seconds: float = 0.0
    caption: str = ""  # what the plot shows, under it
    # for the summary at the top: the paper's headline number, ours, and whether it was reproduced:
    # "yes", "no", "scaled" (the same effect, at this platform's scale: software, 2 cores, veth)
    headline: tuple[str, str] = ("", "")
    verdict: str = "not run"


VERDICT_COLOURS = {"yes": "#1a7f37", "scaled": "#9a6700", "no": "#cf222e", "not run": "#57606a"}


def plt_() -> Any:
    """matplotlib's pyplot, drawing to files (imported when a plot is made)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def whole_numbers(ax: Any) -> None:
    """Ticks only at whole numbers: the axis counts things (TPs, stops, re-plans)."""
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))


def paper_line(ax: Any, y: float, text: str, color: str = "tab:red", vertical: bool = False) -> None:
    """One of the paper's numbers, drawn beside ours (the paper gives numbers, not the data behind its
    curves): a dashed line, labelled in the legend as the paper's."""
    line = ax.axvline if vertical else ax.axhline
    line(y, color=color, ls=(0, (4, 2)), lw=1.1, label=f"paper: {text}")


def save(fig: Any, out: Path, name: str) -> str:
    fig.tight_layout()
    fig.savefig(out / name, dpi=90)
    plt_().close(fig)
    return name


def machine() -> dict[str, str]:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            cwd=Path(__file__).resolve().parent,
            timeout=5,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit = ""
    return {
        "host": platform.node(),
        "cpu": f"{cpu}, {os.cpu_count()} cores",
        "os": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "commit": commit or "unknown",
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }


STYLE = """
body{font-family:sans-serif;max-width:60em;margin:2em auto;line-height:1.35}
table{border-collapse:collapse;margin:.5em 0}
td,th{border:1px solid #bbb;padding:.25em .6em;text-align:left;vertical-align:top}
img{max-width:100%}
figure{margin:1em 0}
figcaption{font-size:.9em;color:#444}
.verdict{font-weight:bold}
@media print{
  body{max-width:none;margin:0;font-size:10pt}
  h2{break-before:page}
  #summary-table,figure,table{break-inside:avoid}
  a{color:inherit;text-decoration:none}
  #machine{font-size:8pt}
}
"""


def write_page(
    out: Path, sections: list[Section], about: dict[str, str], seconds: float, quick: bool
) -> Path:
    e = html.escape

    def verdict(v: str) -> str:
        return f"<span class=verdict style='color:{VERDICT_COLOURS.get(v, '#000')}'>{e(v)}</span>"

    parts = [
        "<!doctype html><meta charset=utf-8><title>cell: the NSDI'22 evaluation</title>",
        f"<style>{STYLE}</style>",
        "<h1>In-network velocity control: the paper's evaluation, reproduced</h1>",
        f"<p>{'Quick run' if quick else 'Full run'} of <code>cell bench paper</code> in {seconds:.0f} s. "
        "<em>Reproduced</em>: yes (the paper's effect, at its number or better), scaled (the same "
        "effect at this platform's scale: a software data plane on two cores and veth links, not a "
        "Tofino), no.</p>",
        "<h2 id=summary>Summary</h2>",
        "<table id=summary-table><tr><th>figure</th><th>the paper</th><th>ours</th><th>reproduced</th></tr>",
    ]
    parts += [
        f"<tr><td><a href='#{e(s.key)}'>{e(s.title)}</a> <small>({e(s.paper_ref)})</small></td>"
        f"<td>{e(s.headline[0])}</td><td>{e(s.headline[1])}</td><td>{verdict(s.verdict)}</td></tr>"
        for s in sections
    ]
    parts += [
        "</table>",
        "<table id=machine>"
        + "".join(f"<tr><th>{e(k)}</th><td>{e(v)}</td></tr>" for k, v in about.items())
        + "</table>",
    ]
    for n, s in enumerate(sections, 1):
        parts.append(f"<h2 id={e(s.key)}>{e(s.title)} <small>({e(s.paper_ref)})</small></h2>")
        if s.png:
            caption = f"<figcaption>Figure {n}. {e(s.caption)}</figcaption>" if s.caption else ""
            parts.append(f"<figure><img src='{e(s.png)}' alt='{e(s.title)}'>{caption}</figure>")
        parts.append("<table class=figures><tr><th>measure</th><th>the paper</th><th>ours</th></tr>")
        parts += [f"<tr><td>{e(a)}</td><td>{e(b)}</td><td>{e(c)}</td></tr>" for a, b, c in s.rows]
        parts.append("</table>")
        if s.notes:
            parts.append(f"<p>{e(s.notes)}</p>")
        parts.append(f"<p><small>time taken by this experiment: {s.seconds:.1f} s</small></p>")
    parts.append(
        "<script type=application/json id=figures>"
        + e(json.dumps({s.key: s.figures for s in sections}))
        + "</script>"
    )
    page = out / "index.html"
    page.write_text("\n".join(parts))
    return page
