"""Run every command that writes figures, and check each figure it writes.

Runs, in this process, ``minetwin simulate`` (the step-response scenario,
1200 s), ``minetwin reproduce NAME --quick`` for each of the paper's results,
``minetwin integration-test`` (30 s, real processes), ``minetwin dem pile``
(a small packed pile) and ``minetwin reference compare`` with the cone
crusher swapped in (its failing signals' overlays). Every figure goes
through ``cosim.plotstyle.save``; a hook reads its matplotlib artists
(``plotstyle.problems``: a title, a [unit] on every axis with tick labels, a
legend entry for every line) before it is written. Prints one line per
figure and exits 1 if any figure breaks the style or any command fails
unexpectedly. The PNGs stay under ``--out`` to look at.

    .venv/bin/python examples/figures_demo.py --out out/figures
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def commands(out: Path) -> list[tuple[str, list[str], tuple[int, ...]]]:
    """(name, minetwin arguments, exit codes that are a success)."""
    cosim_tests = ROOT / "examples" / "cosim_tests"
    runs = [("simulate", ["simulate", str(ROOT / "examples" / "step_response.toml"),
                          "--until", "1200", "--out", str(out / "simulate")], (0,))]
    for name in ("step-response", "mwd", "feed-prediction", "grindability", "sensitivity"):
        runs.append((f"reproduce {name}", ["reproduce", name, "--quick", "--quiet",
                                           "--out", str(out / name)], (0,)))
    runs += [
        ("integration-test", ["integration-test", "--duration", "180", "--speed", "2",
                              "--out", str(out / "integration")], (0,)),
        ("dem pile", ["dem", "pile", "--particles", "300", "--method", "pack",
                      "--settle-time", "2", "--out", str(out / "dem_pile")], (0,)),
        # the cone crusher's coarser product leaves the bands: exit 1 and overlays
        ("reference compare", ["reference", "compare", str(cosim_tests / "plant.toml"),
                               str(cosim_tests / "plant_reference.csv"),
                               "--set", "assets.crusher.fmu=cone_crusher",
                               "--out", str(out / "reference_compare")], (1,)),
    ]
    return runs


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/figures"), help="output folder")
    parser.add_argument("--only", action="append", metavar="NAME",
                        help="run only this command (its name as printed); repeatable")
    args = parser.parse_args(argv)
    from cosim import plotstyle
    from minetwin.cli import main as minetwin

    seen: list[tuple[str, Path, list[str]]] = []
    current = {"name": ""}
    plotstyle.SAVE_HOOKS.append(
        lambda fig, path: seen.append((current["name"], Path(path), plotstyle.problems(fig))))
    failed = []
    for name, arguments, success in commands(args.out):
        if args.only and name not in args.only:
            continue
        current["name"] = name
        start = time.monotonic()
        before = len(seen)
        log = io.StringIO()
        with contextlib.redirect_stdout(log):
            code = minetwin(arguments)
        wrote = len(seen) - before
        print(f"{name}: exit {code}, {wrote} figure(s), {time.monotonic() - start:.0f} s wall",
              file=sys.stderr, flush=True)
        if code not in success or wrote == 0:
            failed.append(f"{name}: exit {code} (expected {success}), {wrote} figure(s)")
    bad = 0
    for name, path, problems in seen:
        print(f"{'ok  ' if not problems else 'BAD '} {path}  ({name})")
        for problem in problems:
            print(f"       {problem}")
        bad += bool(problems)
    print(f"{len(seen)} figure(s), {bad} breaking the style; {len(failed)} command(s) failed")
    for line in failed:
        print(f"failed: {line}", file=sys.stderr)
    return 1 if bad or failed else 0


if __name__ == "__main__":
    sys.exit(main())
