"""``minetwin events``: read a run's macro-tracking event store."""

from __future__ import annotations

import sys
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "events", help="query or export a macro-tracking event store (SQLite)",
        description="Query or export the macro-tracking events of a run (events.sqlite).")
    sub = parser.add_subparsers(dest="events_command", metavar="ACTION", required=True)
    export = sub.add_parser("export", help="export events to Parquet")
    export.add_argument("database", type=Path, help="events.sqlite of a run")
    export.add_argument("--out", type=Path, required=True, help="output folder")
    export.set_defaults(handler=run_export)
    history = sub.add_parser("history", help="print one particle's history as CSV")
    history.add_argument("database", type=Path, help="events.sqlite of a run")
    history.add_argument("particle_id", type=int, help="particle id")
    history.set_defaults(handler=run_history)
    summary = sub.add_parser("summary", help="count events by asset and type")
    summary.add_argument("database", type=Path, help="events.sqlite of a run")
    summary.set_defaults(handler=run_summary)


def _open(path: Path):
    """The store at ``path`` for reading (never written); a file that is not one is refused."""
    from cosim.errors import ValidationError
    from cosim.events import EventStore, EventStoreError

    try:
        return EventStore(path, readonly=True)
    except EventStoreError as exc:
        raise ValidationError("database", "an events.sqlite written by minetwin",
                              str(exc)) from None


def run_export(args) -> int:
    with _open(args.database) as store:
        paths = store.to_parquet(args.out)
    for path in paths:
        print(path)
    return 0


def run_history(args) -> int:
    with _open(args.database) as store:
        frame = store.history(args.particle_id)
    if frame.empty:
        print(f"minetwin events history: no events for particle {args.particle_id}",
              file=sys.stderr)
        return 1
    frame.to_csv(sys.stdout, index=False)
    return 0


def run_summary(args) -> int:
    with _open(args.database) as store:
        frame = store.events()
    table = frame.groupby(["asset", "type"]).agg(events=("event_id", "size"),
                                                  particles=("n_particles", "sum"))
    print(table.to_string())
    return 0
