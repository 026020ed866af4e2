"""`cell bag info DIR`: what a ROS 2 bag holds (topics, types, counts, rates), for users without ROS."""

from __future__ import annotations

import argparse
import json
import sys

from cell.commands import Command, json_arg, register


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=["info"], help="info: topics, message types, counts and rates")
    p.add_argument("bag", help="a rosbag2 directory (MCAP or SQLite storage), or its .mcap / .db3 file")
    json_arg(p)


def run(args: argparse.Namespace) -> int:
    from cell.recorder.bag import BagError, info

    try:
        b = info(args.bag)
    except BagError as exc:
        print(f"cell bag: {exc}", file=sys.stderr)
        return 2
    print(f"bag       {b.path}")
    print(f"storage   {b.storage}, {b.size_bytes / 1e6:.1f} MB")
    print(f"duration  {b.duration_s:.3f} s, {b.messages} messages")
    width = max((len(t.topic) for t in b.topics), default=5)
    tw = max((len(t.msgtype) for t in b.topics), default=4)
    print(f"{'topic':<{width}}  {'type':<{tw}}  {'count':>8}  {'rate':>10}")
    for t in b.topics:
        print(f"{t.topic:<{width}}  {t.msgtype:<{tw}}  {t.count:>8}  {t.rate_hz:>7.1f} Hz")
    if args.json:
        topics = {
            t.topic: {"type": t.msgtype, "count": t.count, "rate_hz": round(t.rate_hz, 3)} for t in b.topics
        }
        print(json.dumps({"bag": str(b.path), "storage": b.storage, "duration_s": round(b.duration_s, 3),
                          "messages": b.messages, "size_bytes": b.size_bytes, "topics": topics}))  # fmt: skip
    return 0


register(
    Command(
        "bag",
        "what a ROS 2 bag holds: topics, types, counts, rates (cell bag info DIR)",
        arguments,
        run,
        rank=30,
    )
)
