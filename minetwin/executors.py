"""The command-line options every batch command shares: which executor runs it."""

from __future__ import annotations

from cosim import batch

EXECUTORS = ("local", "ray")


def add_options(parser, workers: int = 2) -> None:
    """``--executor``, ``--workers``, ``--address`` and ``--retries``."""
    parser.add_argument("--executor", choices=EXECUTORS, default="local",
                        help="local: processes of this machine (default); ray: the Ray cluster "
                             "at --address (pip install 'minetwin[ray]')")
    parser.add_argument("--workers", type=int, default=None,
                        help=f"runs at once (local: processes, default {workers}; ray: "
                             "default the cluster's CPUs)")
    parser.add_argument("--address", default=None, metavar="HOST:PORT",
                        help="with --executor ray: the head node's address (default: the "
                             "environment variable MINETWIN_RAY_ADDRESS)")
    parser.add_argument("--retries", type=int, default=batch.RETRIES,
                        help=f"times a run whose worker died is run again ({batch.RETRIES})")
    parser.set_defaults(default_workers=workers)


def make(args) -> batch.Executor:
    """The executor the options name (a ``ValidationError`` names a bad one)."""
    from cosim.errors import ValidationError

    if args.address is not None and args.executor != "ray":
        raise ValidationError("--address", "given with --executor ray")
    if args.executor == "ray":
        from minetwin.ray_executor import RayExecutor

        if args.workers is not None and args.workers < 1:
            raise ValidationError("--workers", ">= 1", f"got {args.workers}")
        return RayExecutor(args.address, workers=args.workers, retries=args.retries)
    workers = args.default_workers if args.workers is None else args.workers
    return batch.LocalExecutor(workers, retries=args.retries)
