"""`cell bench bilateral`: the Responsive Processor paper's bilateral experiment (Figs. 12-17), run by
cell.teleop.experiment: forces, transparency and the 1 ms loops on the sponge and the wood, the twin
drive's ramp, delay and the e-stop."""

from __future__ import annotations

import argparse
import time

from cell.bench.registry import Bench, Figures, register


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", metavar="DIR", help="where the PNGs go (default runs/bilateral-<time>)")


def _main(args: argparse.Namespace) -> Figures:
    from cell.teleop import experiment

    out = args.out or f"runs/bilateral-{time.strftime('%Y%m%d-%H%M%S')}"
    result = experiment.bench(out)
    return Figures(result, experiment.format_result(result))


register(
    Bench(
        "bilateral",
        "bilateral teleoperation: forces, transparency and the 1 ms loops on the sponge and the wood, the "
        "twin drive's ramp, delay and the e-stop (Responsive Processor paper, Figs. 12-17)",
        _arguments,
        _main,
    )
)
