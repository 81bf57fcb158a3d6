"""REST interface of a paper-scale stockpile: response time per endpoint.

The stockpile asset holds 2,000 t in 20,000 pseudo-particles of 100 kg (the
paper's scale), FIFO (``--model fifo``, the default) or the shipped paper-scale
ROM (``--model rom``), feeder at 1,000 kg/s; the REST server runs in a
background thread on 127.0.0.1 and each endpoint is read ``--repeat`` times
over HTTP. Beside it, the asset's own step of 0.1 s (what the OPC UA
stockpile runs every exchange cycle, its history row included) is timed
``--repeat`` times. Prints one JSON object: median and p95 milliseconds and
response bytes per endpoint, and the step's median and p95 (progress on stderr).

    .venv/bin/python benchmarks/bench_rest.py [--repeat 20] [--model rom]
"""

from __future__ import annotations

import argparse
import sys
import time
import urllib.request
import warnings

import numpy as np

from cosim import jsonio
from surrogate.rest import serve_in_thread
from surrogate.stockpile import StockpileAsset

ENDPOINTS = ("/health", "/totals", "/history?since=0", "/fields?nx=36&ny=18",
             "/particles?limit=20000", "/particles?limit=6000&stride=4", "/feed?horizon=30")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=20,
                        help="reads per endpoint and steps timed (20)")
    parser.add_argument("--model", choices=("fifo", "rom"), default="fifo",
                        help="the stockpile's storage model (fifo)")
    args = parser.parse_args(argv)
    asset = StockpileAsset(args.model, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a ROM warns once if its pile leaves the training ranges
        for k in range(200):  # 200 bins of 10 t from two sources
            asset.receive_bin(k + 1, 10_000.0, (0.2, 0.8)[k % 2], (1.0, 2.0)[k % 2],
                              source=k % 2)
        asset.set_discharge_rate(1000.0)
        for _ in range(10):
            asset.step(0.5)
        step_ms = []
        for _ in range(args.repeat):
            start = time.perf_counter()
            asset.step(0.1)
            step_ms.append((time.perf_counter() - start) * 1e3)
    server = serve_in_thread(asset)
    base = f"http://127.0.0.1:{server.port}"
    results = {}
    try:
        for path in ENDPOINTS:
            times, size = [], 0
            for _ in range(args.repeat):
                start = time.perf_counter()
                with urllib.request.urlopen(base + path, timeout=30) as response:
                    size = len(response.read())
                times.append((time.perf_counter() - start) * 1e3)
            results[path] = {"median_ms": round(float(np.median(times)), 2),
                             "p95_ms": round(float(np.percentile(times, 95)), 2),
                             "bytes": size}
            print(f"{path}: {results[path]}", file=sys.stderr)
    finally:
        server.stop()
    print(jsonio.dumps({"model": args.model, "particles": int(len(asset.particles)),
                        "held_mass_kg": float(asset.particles.mass.sum()),
                        "repeat": args.repeat, "endpoints": results,
                        "step_0.1s": {"median_ms": round(float(np.median(step_ms)), 3),
                                      "p95_ms": round(float(np.percentile(step_ms, 95)), 3)}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
