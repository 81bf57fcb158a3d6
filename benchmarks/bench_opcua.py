"""OPC UA exchange load benchmark (issue 6): >= 100 bins/s for 60 s, nothing lost.

Real processes on 127.0.0.1: the mock 800xA server (CV101 delivers one bin
per simulated second; ``--rate`` sets the speed-up, so bins/s of wall time)
and the stockpile client (FIFO) over Basic256Sha256 SignAndEncrypt. After
``--seconds`` of wall time the clock is frozen, the client drains, both stop
and the exchange is audited. Prints one JSON object.

    .venv/bin/python benchmarks/bench_opcua.py [--rate 100] [--seconds 60]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from cosim import jsonio
from opcua_server.audit import audit
from opcua_server.harness import ServerProcess, StockpileProcess, drain_and_stop, prepare_state


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=120.0,
                        help="bins per wall second offered (default 120, above the 100 target)")
    parser.add_argument("--seconds", type=float, default=60.0, help="wall seconds of load")
    parser.add_argument("--model", default="fifo")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_opcua_") as tmp:
        work = Path(tmp)
        state = prepare_state(work / "state")
        server = ServerProcess(work, state, speed=args.rate)  # default config: 1 bin/s
        client = None
        try:
            client = StockpileProcess(work, state, server.url, model=args.model, rest=True)
            start = time.monotonic()
            while (elapsed := time.monotonic() - start) < args.seconds:
                time.sleep(min(10.0, args.seconds - elapsed))
                print(f"bench_opcua: {time.monotonic() - start:.0f} s", file=sys.stderr, flush=True)
            wall = time.monotonic() - start
            ledger, summary = drain_and_stop(server, client, timeout=120)
        finally:
            for proc in (client, server):
                if proc is not None:
                    proc.stop()
    result = audit(ledger, summary)
    result.pop("lost_examples"), result.pop("duplicated_examples")
    sim_per_wall = args.rate
    out = {
        "benchmark": "opcua_exchange", "target_bins_per_s": 100.0, "load_wall_s": wall,
        "bins_per_wall_s": result["bins_in"] / (ledger["time_s"] / sim_per_wall),
        **result,
        "max_lag_wall_s": ledger["max_surrogate_lag_s"] / sim_per_wall,
        "step_time_p99_ms": summary["step_time_p99_ms"], "exchange_cycles": summary["cycles"],
        "reconnects": summary["reconnects"],
    }
    out["passed"] = (out["bins_per_wall_s"] >= 100.0 and out["tracking_ids_lost"] == 0
                     and out["tracking_ids_duplicated"] == 0
                     and out["mass_balance_rel_error"] < 1e-9)
    print(jsonio.dumps(out, indent=2))
    return 0 if out["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
