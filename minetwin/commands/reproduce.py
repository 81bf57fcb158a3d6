"""``minetwin reproduce NAME``: reproduce one of the paper's results.

Each NAME maps to a module (``REPRODUCTIONS``) exposing ``DESCRIPTION`` and
``reproduce(out_dir, *, quick, progress) -> (summary, failed_checks)``; the
module writes its figures and ``out_dir/summary.json``. Other analyses add
their NAME here.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

from cosim import jsonio
from minetwin import executors

REPRODUCTIONS: dict[str, str] = {
    "step-response": "cosim.analyses.step_response",
    "mwd": "cosim.analyses.mwd",
    "feed-prediction": "cosim.analyses.feed_prediction",
    "grindability": "cosim.analyses.grindability",
    "sensitivity": "cosim.analyses.sensitivity",
    "pile-states": "surrogate.rom.pile_states",
}
"""Reproducible results by name -> module path."""

BATCHES = {"sensitivity"}
"""The reproductions made of a batch of independent runs: their ``reproduce``
also takes ``executor`` (``cosim.batch``), chosen with --executor/--workers."""


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "reproduce", help="reproduce a result of the paper (figures + summary.json)",
        description="Reproduce a result of the paper. NAMEs: " + ", ".join(REPRODUCTIONS)
        + ". Writes PNG figures and DIR/summary.json; exit code 1 when the paper's "
          "mechanism does not show (the failed checks are printed).")
    parser.add_argument("name", choices=sorted(REPRODUCTIONS), metavar="NAME",
                        help=f"one of {', '.join(sorted(REPRODUCTIONS))}")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    parser.add_argument("--quick", action="store_true", help="shorter runs (for tests/CI)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    executors.add_options(parser, workers=1)
    parser.set_defaults(handler=run)


def run(args) -> int:
    from cosim.errors import ValidationError
    from cosim.master import CosimulationError

    module = importlib.import_module(REPRODUCTIONS[args.name])
    options = {}
    if args.name in BATCHES:
        options["executor"] = executors.make(args)
    elif args.executor != "local" or args.workers not in (None, 1):
        raise ValidationError("--executor/--workers", f"left out for {args.name} (one run; "
                              f"batches: {', '.join(sorted(BATCHES))})")
    try:
        summary, failed = module.reproduce(args.out, quick=args.quick, progress=not args.quiet,
                                           **options)
    except CosimulationError as exc:
        print(f"minetwin reproduce: run failed: {exc}", file=sys.stderr)
        return 1
    finally:
        if "executor" in options:
            options["executor"].close()
    print(jsonio.dumps(summary, indent=2, sort_keys=True))
    print(args.out / "summary.json")
    for problem in failed:
        print(f"minetwin reproduce {args.name}: check failed: {problem}", file=sys.stderr)
    return 1 if failed else 0
