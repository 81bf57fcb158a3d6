"""The ``minetwin`` command line.

Each subcommand lives in its own module that exposes
``register(subparsers)``; heavy imports happen inside the handlers so that
``minetwin --help`` stays fast. Exit codes: 0 success, 1 a failed run or
check, 2 bad usage or bad input (message on stderr).
"""

from __future__ import annotations

import argparse
import importlib
import sys

from cosim.errors import ValidationError, interruption

COMMAND_MODULES = (
    "minetwin.commands.simulate",
    "minetwin.commands.reproduce",
    "minetwin.commands.sweep",
    "minetwin.commands.integration",
    "minetwin.commands.serve",
    "minetwin.commands.stockpile",
    "minetwin.commands.monitor",
    "minetwin.commands.dem",
    "minetwin.commands.rom",
    "minetwin.commands.fidelity",
    "minetwin.commands.coupling",
    "minetwin.commands.fmus",
    "minetwin.commands.reference",
    "minetwin.commands.events",
    "minetwin.commands.sizes",
)
"""Modules that add subcommands, in the order ``--help`` lists them."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="minetwin",
        description="MineTwin: particle-based mine-to-mill material tracking.")
    parser.add_argument("--version", action="version",
                        version=f"%(prog)s {importlib.import_module('cosim').__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def _innermost_parser(parser: argparse.ArgumentParser, args) -> argparse.ArgumentParser:
    """The (sub)parser of the command that was chosen, for its own usage line."""
    while True:
        actions = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        chosen = actions and getattr(args, actions[0].dest, None)
        if not chosen or chosen not in actions[0].choices:
            return parser
        parser = actions[0].choices[chosen]


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # argparse would blame the top level; the subcommand's usage helps more
        _innermost_parser(parser, args).error(f"unrecognized arguments: {' '.join(unknown)}")
    if not getattr(args, "handler", None):
        parser.print_help()
        return 2
    try:
        return int(args.handler(args) or 0)
    except ValidationError as exc:
        print(f"minetwin {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a path that cannot be read or written: bad input, not a bug
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"minetwin {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, SystemError) as exc:  # SystemError: Ctrl-C inside a numba kernel
        if not isinstance(interruption(exc), KeyboardInterrupt):
            raise
        print(f"minetwin {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
