"""`cell bench paper`: the NSDI'22 evaluation reproduced in one run, written as one web page.

Each experiment measures what one figure or table of the paper shows, with our
figures beside the paper's in a table and our plot (matplotlib PNG) beside
them.  The page says on what machine, at which commit and when it ran, and
how long each part took.  `--quick` runs every experiment smaller (fewer
moves, shorter trials); `--only` picks experiments by name.

What each experiment runs:
- accuracy: a live cell (bus, data plane, two MuJoCo arms) and the controller:
  stop error (Sec. 7.3), tool path error at TPs (Sec. 7.4, Fig. 11),
  synchronised starts (Sec. 7.2, Fig. 9), re-planning and the start-state
  prediction of Sec. 6.1 (Fig. 8), ours next to the paper's binned formula;
- pid: the closed loop without sockets (cell.bench.loopsim) with the data
  plane's controller and a host PID on the same MuJoCo arm and motions, the
  baseline of Fig. 11;
- latency: status-to-command time of the data plane service at 10-300 robots
  at 500 Hz x 6 joints (Sec. 7.1; the paper's is a Tofino's, in ns);
- churn: the fleet bench's arms moving, without and with the paper's table churn
  beside them (+1.6K / -1.6K TPs a second; Sec. 7.4, Fig. 12);
- xdp-background: the XDP pipeline's response time while ordinary traffic passes through it
  at rising rates, next to plain forwarding (Sec. 7.1; root);
- background: robots and ordinary traffic through one congested egress port of the data plane,
  one shared FIFO against strict priority, in network namespaces (Appendix C, Fig. 14; root);
- resubmission: Algorithm 1's one TP step per pass, and what each further
  pass (resubmission) costs, for TP rates up to 4x the status rate;
- scaling: the table capacity against robots x episode x TP rate
  (Appendix A, Fig. 13) and the update time t_upd against batch size;
- resources: the memory the tables take against arms for 50/100/200 TPs an arm, on
  the loaded XDP object and the numpy Tables, and the program's size (Fig. 13a-b);
- episodes: t_upd through the live data plane service, and the arms it keeps fed
  against the episode length at 10 and 43 TPs/s, checked (Fig. 13c-d);
- x86: a driver process per arm (the paper's ROS driver's shape) against the data
  plane, arms on one core at 500 Hz (Appendix B).

The experiments live by subject: motion.py (accuracy, pid), network.py (latency,
resubmission, background, xdp-background), scale.py (the rest); page.py holds the
Section each returns and the page they are written to.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cell.bench.paper.motion import accuracy, pid
from cell.bench.paper.network import background, latency, resubmission, xdp_background
from cell.bench.paper.page import Log, Section, machine, write_page
from cell.bench.paper.scale import churn, episodes, resources, scaling, x86
from cell.bench.registry import Bench, Figures, log, register
from cell.jsonfields import JsonFields

EXPECTED_S = {
    "accuracy": (55, 180),
    "pid": (5, 10),
    "latency": (12, 20),
    "churn": (35, 60),
    "background": (50, 150),
    "xdp-background": (25, 60),
    "resubmission": (5, 20),
    "scaling": (2, 5),
    "resources": (5, 8),
    "episodes": (15, 25),
    "x86": (45, 70),
}

EXPERIMENTS: dict[str, Callable[[bool, Path, Log], list[Section]]] = {
    "accuracy": accuracy,
    "pid": pid,
    "latency": latency,
    "churn": churn,
    "background": background,
    "xdp-background": xdp_background,
    "resubmission": resubmission,
    "scaling": scaling,
    "resources": resources,
    "episodes": episodes,
    "x86": x86,
}


@dataclass
class PaperResult(JsonFields):
    """What `cell bench paper` wrote: the page, how long it took, and each section's figures by its key
    (the sections are chosen by --only, so a map)."""

    page: str
    seconds: float
    quick: bool
    experiments: list[str]
    figures: dict[str, dict[str, Any]]


def run(quick: bool, out: str, only: list[str] | None = None, log: Log = print) -> PaperResult:
    names = only or list(EXPERIMENTS)
    unknown = [n for n in names if n not in EXPERIMENTS]
    if unknown:
        raise ValueError(f"no experiment {', '.join(unknown)} (there are: {', '.join(EXPERIMENTS)})")
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    sections: list[Section] = []
    expect = {n: EXPECTED_S[n][0 if quick else 1] for n in names}
    log(f"{len(names)} experiments, about {sum(expect.values()) / 60:.0f} min here")
    for i, name in enumerate(names, 1):
        left = sum(expect[n] for n in names[i - 1 :])
        log(
            f"[{i}/{len(names)}] {name}: about {expect[name]} s "
            f"({time.monotonic() - t_start:.0f} s so far, about {left} s to go)"
        )
        t0 = time.monotonic()
        got = EXPERIMENTS[name](quick, folder, log)
        for s in got:
            s.seconds = (time.monotonic() - t0) / len(got)
        sections += got
    seconds = time.monotonic() - t_start
    page = write_page(folder, sections, machine(), seconds, quick)
    log(f"wrote {page}")
    return PaperResult(
        page=str(page),
        seconds=round(seconds, 1),
        quick=quick,
        experiments=names,
        figures={s.key: s.figures for s in sections},
    )


def format_result(r: PaperResult) -> str:
    lines = [f"{r.page} ({r.seconds} s)"]
    for key, figs in r.figures.items():
        shown = ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in figs.items())
        lines.append(f"  {key}: {shown}")
    return "\n".join(lines)


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="every experiment smaller (under 5 minutes)")
    p.add_argument("--out", help="where to write index.html and the plots (default runs/paper-<time>)")
    p.add_argument("--only", help=f"comma-separated experiments: {','.join(EXPERIMENTS)}")


def _main(args: argparse.Namespace) -> Figures:
    out = args.out or f"runs/paper-{time.strftime('%Y%m%d-%H%M%S')}"
    only = [x for x in args.only.split(",") if x] if args.only else None
    result = run(args.quick, out, only, log=log)
    return Figures(result, format_result(result))


register(
    Bench(
        "paper",
        "the NSDI'22 paper's evaluation in one run: every experiment, our figures next to the paper's, "
        "written to DIR/index.html with plots",
        _arguments,
        _main,
    )
)
