"""The `cell` command line: the commands of cell.commands, each registered by its own module.

Only the chosen command's arguments are built (a bench's module, say, is not imported for
`cell status`), so every command starts in the time its own imports take.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys

from cell import __version__
from cell.commands import EXIT_CONFIG, discover, literal
from cell.config import ConfigError


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; with `argv`, only the command it names gets its arguments (None: all of them)."""
    parser = argparse.ArgumentParser(
        prog="cell",
        description="Run and inspect a networked industrial robot cell (README.md).",
    )
    parser.add_argument("--version", action="version", version=f"cell {__version__}")
    parser.add_argument(
        "--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"], help="default: INFO"
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    commands = discover()
    chosen = None if argv is None else next((a for a in argv if a in commands), "")
    for name, cmd in commands.items():
        p = sub.add_parser(name, help=literal(cmd.help), description=literal(cmd.description))
        if chosen is None or chosen == name:
            cmd.arguments(p)
        p.set_defaults(func=cmd.run, hard_exit=cmd.hard_exit)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser(argv).parse_args(argv)
    logging.basicConfig(
        level=args.log_level,
        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    # (PyOpenGL, imported under MuJoCo's renderer, says at INFO that an optional accelerator is absent:
    # noise in every command's output)
    logging.getLogger("OpenGL").setLevel(logging.WARNING)
    try:
        rc = args.func(args)
        if args.hard_exit:
            # skip interpreter teardown: everything is closed, and extension modules (ruckig's
            # nanobind) would print reference-leak reports at exit that are not ours to fix
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(rc)
        return rc
    except ConfigError as exc:
        print(f"cell: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    except BrokenPipeError:  # (`cell status | head`: the reader has what it wanted)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
        return 141  # what a shell reports for a writer that SIGPIPE ended
    except KeyboardInterrupt:
        return 130
    except Exception as exc:  # no traceback for what is not a bug: no cell to talk to
        from cell.bus import BusUnavailable  # (lazy: `cell --help` loads no ZeroMQ)

        if not isinstance(exc, BusUnavailable):
            raise
        print(f"cell {args.command}: no cell answered ({exc})", file=sys.stderr)
        return 1
