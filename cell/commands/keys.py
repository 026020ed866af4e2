"""`cell keys generate`: CurveZMQ certificates for a bus that leaves loopback."""

from __future__ import annotations

import argparse
import sys

from cell.commands import Command, register


def arguments(p: argparse.ArgumentParser) -> None:
    ksub = p.add_subparsers(dest="keys_command", required=True, metavar="ACTION")
    q = ksub.add_parser(
        "generate",
        help="the forwarder's certificate and one per client, each client allow-listed",
        description="Writes DIR/server.key(_secret), DIR/<client>.key(_secret) and DIR/allowed/<client>.key "
        "(cell/bus/curve.py). Existing certificates are kept: run it again to add clients. Then set "
        "[bus] curve = true, keys = DIR and client = NAME on every host.",
    )
    q.add_argument("--dir", default="keys", help="where (default: keys)")
    q.add_argument(
        "--client", nargs="+", default=["cell"], metavar="NAME", help="client names (default: cell)"
    )


def run(args: argparse.Namespace) -> int:
    from cell.bus import curve

    bad = [c for c in args.client if not c.replace("-", "").replace("_", "").isalnum() or c == curve.SERVER]
    if bad:
        print(
            f"error: bad client name {bad[0]!r} (letters, digits, - and _; not {curve.SERVER!r})",
            file=sys.stderr,
        )
        return 2
    written = curve.generate(args.dir, args.client)
    for path in written:
        print(path)
    print(f"{len(written)} file(s) in {args.dir}; the .key_secret files are private (mode 600)")
    return 0


register(Command("keys", "CurveZMQ keys for a bus that leaves loopback", arguments, run, rank=31))
