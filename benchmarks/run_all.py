"""Run every benchmark in this folder and collect their JSON.

Each ``bench_*.py`` prints one JSON object on stdout (progress on stderr);
this runner stores it as ``OUT/<name>.json`` and prints a one-line status
per benchmark. Exit code 1 if any benchmark failed.

    .venv/bin/python benchmarks/run_all.py --out out/bench [--only fmu,dem]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from cosim import jsonio

HERE = Path(__file__).resolve().parent


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench"), help="output folder")
    parser.add_argument("--only", default="",
                        help="comma-separated names (e.g. foundation,dem) instead of all")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    wanted = {name.strip() for name in args.only.split(",") if name.strip()}
    scripts = sorted(HERE.glob("bench_*.py"))
    if wanted:
        scripts = [s for s in scripts if s.stem.removeprefix("bench_") in wanted]
    failed = 0
    for script in scripts:
        name = script.stem.removeprefix("bench_")
        start = time.perf_counter()
        result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                                cwd=HERE.parent)
        wall = time.perf_counter() - start
        try:
            data = json.loads(result.stdout[result.stdout.index("{"):])
        except ValueError:
            data = None
        if result.returncode != 0 or data is None:
            failed += 1
            print(f"FAIL {name} ({wall:.0f} s): exit {result.returncode}\n"
                  f"{result.stderr[-2000:]}", file=sys.stderr)
            continue
        jsonio.write(args.out / f"{name}.json", data, indent=2)
        print(f"ok   {name} ({wall:.0f} s) -> {args.out / (name + '.json')}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
