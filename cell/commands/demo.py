"""`cell demo`: the main job. The default cell, a bundled task script, a recording, a summary."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cell.commands import Command, config_arg, load, register
from cell.commands.up import with_bag, with_rerun


def arguments(p: argparse.ArgumentParser) -> None:
    config_arg(p)
    p.add_argument("--out", metavar="PATH.rrd", help="where to record (default runs/<timestamp>.rrd)")
    p.add_argument("--bag", metavar="DIR", help="write the run as a ROS 2 bag (rosbag2, MCAP) in DIR as well")


def run(args: argparse.Namespace) -> int:
    import shutil
    import subprocess
    import time

    from cell import aio, demo
    from cell.master import run_script

    stamp = time.strftime("%Y%m%d-%H%M%S")
    rrd = Path(args.out or f"runs/{stamp}.rrd").resolve()
    rrd.parent.mkdir(parents=True, exist_ok=True)
    config = load(args, {"recorder": {"mode": "save", "path": str(rrd)}})
    config = with_rerun(config, ["save", str(rrd)])
    if args.bag:
        config = with_bag(config, str(Path(args.bag).resolve()))
    effective = rrd.with_suffix(".toml")
    effective.write_text(config.to_toml())
    print(f"cell demo: the default cell, recorded to {rrd}", flush=True)
    rc = aio.run(run_script(Path(demo.__file__), config, effective, up=True))
    rerun = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
    if rrd.exists() and Path(rerun).exists():
        check = subprocess.run(
            [rerun, "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120
        )
        verdict = "verified" if check.returncode == 0 else f"NOT verified: {check.stderr.strip()[-300:]}"
        print(f"recording {rrd} ({rrd.stat().st_size / 1e6:.1f} MB): {verdict}")
        print(f"open it with: {rerun} {rrd}   (or watch live: cell up --rerun spawn | serve)")
    if args.bag:
        print(f"ROS 2 bag: {Path(args.bag).resolve()} (cell bag info {args.bag}; ros2 bag info, Foxglove)")
    return rc


register(
    Command(
        "demo",
        "the main job: the default cell runs a bundled task, recorded for Rerun",
        arguments,
        run,
        rank=1,
    )
)
