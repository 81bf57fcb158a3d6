"""``minetwin sweep``: the grid of a plant scenario's settings, one batch of runs.

Each ``--set KEY=V1,V2,...`` names a setting of the scenario file by its
dotted path (``assets.left.grade``, ``assets.trucks.trucks.0.speed_m_s``: a number picks
an element of an array of tables) and the values it takes; the runs are every
combination of them times ``--seeds N`` seeds (the scenario's seed, +1, ...,
+N-1). Each run is ``minetwin simulate``'s (``cosim.scenario.run_scenario``)
into its own folder ``DIR/runs/<key>``; ``DIR/summary.parquet`` has one row
per run: its settings, seed, status and error, and its summary's numbers.
Runs are stored by the content key of their inputs (``cosim.batch``), so a
sweep started again skips the runs already done.
"""

from __future__ import annotations

import itertools
import sys
import tomllib
from pathlib import Path

from minetwin import executors


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "sweep", help="run the grid of a scenario's settings (x seeds); one Parquet table",
        description="Run a plant scenario for every combination of the --set values and "
                    "--seeds seeds, each into DIR/runs/<key> (what `minetwin simulate` writes), "
                    "and write DIR/summary.parquet (one row per run: settings, seed, status, "
                    "error, summary) and DIR/sweep.json. A run that fails is recorded and the "
                    "sweep goes on (exit code 1 at the end); runs already done in DIR are "
                    "skipped. Progress on stderr.")
    parser.add_argument("scenario", type=Path, help="scenario TOML, e.g. examples/step_response.toml")
    parser.add_argument("--set", action="append", default=[], dest="settings",
                        metavar="KEY=V1,V2,...",
                        help="a setting and its values (TOML literals: 1.5, true, \"fifo\"); "
                             "repeatable: the grid is every combination")
    parser.add_argument("--seeds", type=int, default=1, metavar="N",
                        help="seeds per setting: the scenario's seed and the N-1 after it (1)")
    parser.add_argument("--until", type=float, default=None, metavar="SECONDS",
                        help="simulated time [s] of each run (default: the scenario's)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="output folder (created; runs already in it are skipped)")
    executors.add_options(parser, workers=2)
    parser.set_defaults(handler=run)


def parse_setting(text: str) -> tuple[str, list]:
    """``KEY=V1,V2`` -> (KEY, [V1, V2]) with each value read as a TOML literal
    (a bare word is a string)."""
    from cosim.errors import ValidationError

    key, sep, values = text.partition("=")
    if not sep or not key.strip() or not values.strip():
        raise ValidationError("--set", "KEY=V1,V2,... (e.g. assets.left.grade=0.2,0.3)",
                              f"got {text!r}")
    parsed = []
    for value in values.split(","):
        try:
            parsed.append(tomllib.loads(f"v = {value.strip()}")["v"])
        except tomllib.TOMLDecodeError:
            parsed.append(value.strip())
    return key.strip(), parsed


def apply_setting(config: dict, key: str, value) -> None:
    """Set the dotted ``key`` of ``config`` (which must exist) to ``value``."""
    from cosim.errors import ValidationError

    *parents, last = key.split(".")
    node = config
    for depth, part in enumerate(parents + [last]):
        where = ".".join((parents + [last])[:depth + 1])
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise ValidationError("--set", f"an index below {len(node)} at {where}",
                                      f"got {part!r}")
            part = int(part)
        elif not isinstance(node, dict) or part not in node:
            keys = sorted(node) if isinstance(node, dict) else []
            raise ValidationError("--set", f"a key of the scenario; at {where} one of {keys}",
                                  f"got {key!r}")
        if depth == len(parents):
            node[part] = value
        else:
            node = node[part]


def plan(scenario: Path, settings: list[str], seeds: int, until: float | None) -> list:
    """The sweep's tasks (``cosim.batch.Task``), each point's scenario validated."""
    import copy

    from cosim import batch
    from cosim.errors import ValidationError
    from cosim.scenario import load, validate

    if seeds < 1:
        raise ValidationError("--seeds", ">= 1", f"got {seeds}")
    if until is not None and not until > 0:
        raise ValidationError("--until", "> 0 s", f"got {until!r}")
    base = load(scenario)
    grid = [parse_setting(text) for text in settings]
    keys = [key for key, _ in grid]
    if len(set(keys)) != len(keys):
        raise ValidationError("--set", "each key once", f"got {keys}")
    tasks = []
    for values in itertools.product(*[values for _, values in grid]):
        config = copy.deepcopy(base)
        point = dict(zip(keys, values))
        for key, value in point.items():
            apply_setting(config, key, value)
        try:
            config = validate(config)
        except ValidationError as exc:
            raise ValidationError(f"--set {exc.field}", exc.allowed,
                                  f"{exc.detail + '; ' if exc.detail else ''}at {point}") from None
        for k in range(seeds):
            seed = int(base["simulation"]["seed"]) + k
            label = ", ".join(f"{key}={value}" for key, value in point.items())
            tasks.append(batch.Task(f"{label or 'scenario'}, seed {seed}", run_point,
                                    {"config": config, "settings": point, "until": until,
                                     "scenario_name": scenario.stem}, seed=seed,
                                    writes_folder=True))
    return tasks


def run_point(*, config: dict, settings: dict, until, scenario_name: str, seed: int,
              folder: str) -> dict:
    """One run of the sweep into ``folder``; its summary (one task of the batch)."""
    from cosim.scenario import run_scenario

    _, summary = run_scenario(config, folder, until=until, seed=seed, progress=False,
                              scenario_name=scenario_name)
    return summary


def table(records: list[dict]):
    """One row per run: name, key, status, error, seed, ``set.<key>`` and the summary."""
    import pandas as pd

    rows = []
    for record in records:
        row = {"name": record["name"], "key": record["key"], "status": record["status"],
               "error": record.get("error"), "seed": record["seed"],
               "folder": record.get("folder"), "code_version": record.get("code_version"),
               "host": record.get("host")}
        row.update({f"set.{k}": v for k, v in record["inputs"]["settings"].items()})
        row.update({k: v for k, v in (record.get("value") or {}).items()
                    if k not in row and (v is None or isinstance(v, (bool, int, float, str)))})
        rows.append(row)
    return pd.DataFrame(rows)


def run(args) -> int:
    from cosim import batch, jsonio

    tasks = plan(args.scenario, args.settings, args.seeds, args.until)
    args.out.mkdir(parents=True, exist_ok=True)
    with executors.make(args) as executor:
        records = batch.run_batch(tasks, executor, store=args.out, label="sweep")
    frame = table(records)
    frame.to_parquet(args.out / "summary.parquet", index=False)
    result = batch.summary(records)
    jsonio.write(args.out / "sweep.json", {"scenario": str(args.scenario),
                                           "settings": args.settings, "seeds": args.seeds,
                                           "until_s": args.until, **result})
    print(f"sweep: {result['done']} of {result['runs']} runs done; "
          f"{args.out / 'summary.parquet'}", file=sys.stderr)
    for failure in result["failed"]:
        print(f"minetwin sweep: run {failure['name']} ({failure['key']}) failed: "
              f"{failure['error']}", file=sys.stderr)
    return 1 if result["failed"] else 0
