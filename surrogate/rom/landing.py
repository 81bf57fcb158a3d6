"""Where the inflow joins the bulk: the DEM against the ROM's surface layer.

The ROM's surface layer (``surrogate.rom.surface_dem``; paper sections "Digital
twin as a distributed particle simulation" and "Integration test": resolved DEM
for the particles impacting the pile) drops each incoming particle from the
inlet onto a fixed bed laid along the bulk, lets it join the bulk 0.05 s after
its first contact, and rolls it on by the angle-of-repose rule
(``surrogate.rom.surface.deposit``). This module measures how far from the
inlet that puts the newcomers against where the DEM has them, on the piles of a
training design, so that ``RomStorage(landing_spread=...)`` can be set from the
design rather than from the scenes a model is scored on.

One measurement (``measure``): a pile of the design, laid out and settled as the
design does (``paper_design.build_pile``), runs in the DEM for ``seconds`` with
its feeder at ``rate`` [kg/s] and the same rate fed at the inlet, one control
step (``doe.CONTROL_STEP``) of the lot feed at a time (``paper_design.emit_feed``).
At each step the step's newcomers also go to the ROM's surface layer (the
model's DEM and container, as ``RomStorage`` builds it) over the DEM's
bulk as it stands at their entry (``doe.bulk_only``), for one step, and those
that joined are deposited on that bulk's surface: where the ROM puts them into
its bulk. A DEM newcomer is read ``doe.BULK_AGE`` (4 s) after its entry, the age
from which the design's fields, and so the ROM's regression, count a particle as
bulk. Reported, as x - inlet_x [m] over the newcomers both place: quantiles and
standard deviations, and the extra spread sqrt(var_DEM - var_ROM) [m] (0 when
the ROM's is the wider), the standard deviation of the normal offset that gives
the ROM's newcomers the DEM's variance. ``summary`` gives its mean and spread
over the measurements.

Run (default: the four measurements of surrogate/rom/README.md, "Where the
inflow joins the bulk"; about 30 CPU minutes)::

    python -m surrogate.rom.landing --out DIR [--run PILE:RATE:SECONDS:SEED ...] [--workers 2]

Writes ``landing.json`` (strict JSON) and prints one line per measurement and
the summary.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from cosim import jsonio
from cosim.errors import ValidationError, check_finite_range

QUANTILES = (5, 10, 25, 50, 75, 90, 95)
"""Percentiles [%] of x - inlet_x reported for the DEM and the surface layer."""

PAPER_RUNS = (("base_1700t", 2000.0, 40, 0), ("base_1700t", 1200.0, 40, 0),
              ("partial_1200t", 2000.0, 30, 1), ("base_1700t", 1600.0, 30, 2))
"""The measurements on the paper design (pile, rate [kg/s], seconds, seed): both
base piles, 1.2-2 t/s in and out."""

FIRST_TRACKING_ID = 100_000
"""Tracking id of the first fed lot (above the laid-out piles' lots)."""


def check_run(design, pile: str, rate: float, seconds, field: str = "") -> float:
    """Refuse a measurement ``measure`` cannot make; returns the rate [kg/s]. Errors
    name ``field`` (e.g. "--run": "--run", "--run rate", "--run seconds"), or
    "pile", "rate" and "seconds" without one."""
    from surrogate.rom import doe

    piles = [p.name for p in design.piles]
    if pile not in piles:
        raise ValidationError(field or "pile", f"one of {piles}", f"got {pile!r}")
    rate = float(check_finite_range(f"{field} rate".strip(), rate, 0.0, low_open=True,
                                    unit="kg/s"))
    if int(seconds) != seconds or seconds <= doe.BULK_AGE:
        raise ValidationError(f"{field} seconds".strip(),
                              f"a whole number of seconds above {doe.BULK_AGE:g}",
                              f"got {seconds!r}")
    return rate


def measure(design, pile: str, rate: float, seconds: int, seed: int = 0, model=None,
            progress=None) -> dict:
    """One measurement (module docstring) on ``design``'s pile ``pile`` fed and drained
    at ``rate`` [kg/s] for ``seconds`` [s]; ``seed`` draws the feed's lots and the
    surface layer's random numbers; ``model`` (default the default ROM,
    ``storage.DEFAULT_MODEL``) gives the surface layer's DEM and container."""
    from surrogate.rom import doe
    from surrogate.rom import paper_design as pd
    from surrogate.rom.storage import _dem_config, load_model
    from surrogate.rom.surface import column_width, deposit, surface_heights
    from surrogate.rom.surface_dem import SurfaceDem

    rate = check_run(design, pile, rate, seconds)
    tic, cpu0 = time.perf_counter(), time.process_time()
    model = load_model(model)
    container = model.container
    dem, _ = pd.build_pile(design, design.pile(pile))
    surface = SurfaceDem(_dem_config(model.dem_config), container,
                         rng=np.random.default_rng(11 + seed))
    rng = np.random.default_rng(7 + seed)
    feed = doe.LotFeed(FIRST_TRACKING_ID, 3 + seed)
    dem.set_discharge_rate(rate, outlet=0)
    dem.discharged()
    age = int(round(doe.BULK_AGE / doe.CONTROL_STEP))
    entered, rom_x, dem_x = [], {}, {}
    steps = int(round(seconds / doe.CONTROL_STEP))
    for step in range(steps):
        bulk = doe.bulk_only(dem.snapshot())
        first = dem.n
        pd.emit_feed(dem, feed, rate * doe.CONTROL_STEP)
        entered.append(dem.id[first:].copy())
        width = column_width(container, float(np.median(bulk["mass"])))
        surface.add(dem.id[first:], dem.mass[first:])
        ids, mass, position = surface.advance(doe.CONTROL_STEP, width, bulk["position"],
                                              bulk["mass"])
        if ids.size:
            heights = surface_heights(container, width, bulk["position"], bulk["mass"])
            rest = deposit(container, width, heights, mass, rng, landing_x=position[:, 0])
            rom_x.update(zip(ids.tolist(), rest[:, 0].tolist()))
        reason = doe.advance_guarded(dem, doe.CONTROL_STEP)
        if reason:
            raise ValidationError("rate", "a stable DEM run", f"the DEM blew up at "
                                  f"t = {dem.time:.2f} s: {reason}")
        dem.discharged()
        if step + 1 >= age:  # the newcomers of step + 1 - age reach the bulk age now
            cohort = entered[step + 1 - age]
            keep = np.isin(dem.id, cohort)
            dem_x.update(zip(dem.id[keep].tolist(), dem.pos[keep, 0].tolist()))
        if progress is not None and (step + 1) % 10 == 0:
            progress(f"landing {pile} at {rate:g} kg/s, seed {seed}: {step + 1}/{steps} s, "
                     f"{time.perf_counter() - tic:.0f} s of wall time")
    both = [i for i in dem_x if i in rom_x]
    dem_offset = np.array([dem_x[i] for i in both]) - container.inlet_x
    rom_offset = np.array([rom_x[i] for i in both]) - container.inlet_x
    return {"pile": pile, "rate_kg_s": rate, "seconds": int(seconds), "seed": int(seed),
            "newcomers": len(both), "bulk_age_s": float(doe.BULK_AGE),
            "inlet_x_m": float(container.inlet_x), "quantiles_pct": list(QUANTILES),
            "dem_quantiles_m": np.percentile(dem_offset, QUANTILES).tolist(),
            "rom_quantiles_m": np.percentile(rom_offset, QUANTILES).tolist(),
            "dem_std_m": float(dem_offset.std()), "rom_std_m": float(rom_offset.std()),
            "extra_spread_m": float(np.sqrt(max(dem_offset.var() - rom_offset.var(), 0.0))),
            "wall_s": time.perf_counter() - tic, "cpu_s": time.process_time() - cpu0}


def summary(measurements: list[dict]) -> dict:
    """Mean, sample standard deviation, min and max of the extra spread [m]."""
    extra = np.array([m["extra_spread_m"] for m in measurements])
    return {"extra_spread_m": {"mean": float(extra.mean()),
                               "std": float(extra.std(ddof=1)) if extra.size > 1 else 0.0,
                               "min": float(extra.min()), "max": float(extra.max()),
                               "n": int(extra.size)}}


def parse_run(text: str) -> tuple:
    """``PILE:RATE:SECONDS:SEED`` -> (pile, rate [kg/s], seconds, seed)."""
    parts = text.split(":")
    try:
        if len(parts) != 4:
            raise ValueError
        return parts[0], float(parts[1]), int(parts[2]), int(parts[3])
    except ValueError:
        raise ValidationError("--run", "PILE:RATE:SECONDS:SEED, e.g. base_1700t:2000:30:0",
                              f"got {text!r}") from None


def _line(m: dict) -> str:
    return (f"{m['pile']} at {m['rate_kg_s']:g} kg/s, {m['seconds']} s, seed {m['seed']}: "
            f"{m['newcomers']} newcomers; x - inlet_x sd DEM {m['dem_std_m']:.2f} m, "
            f"surface layer {m['rom_std_m']:.2f} m; extra spread {m['extra_spread_m']:.2f} m")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m surrogate.rom.landing",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--design", default="paper", help="design whose piles are used (paper)")
    parser.add_argument("--run", action="append", default=None, metavar="PILE:RATE:SECONDS:SEED",
                        help="one measurement (repeatable; default the paper design's four)")
    parser.add_argument("--model", default=None,
                        help="ROM model file (default: the default ROM, "
                             "data/paper_rom_loose.npz)")
    parser.add_argument("--workers", type=int, default=2, help="processes (default 2)")
    args = parser.parse_args(argv)

    def progress(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    try:
        from cosim import batch
        from surrogate.rom import paper_design as pd

        design = pd.get_design(args.design)
        if not args.run and args.design != "paper":
            raise ValidationError("--run", "given for a design other than paper (the default "
                                  "measurements are on the paper design's piles)")
        runs = [parse_run(text) for text in args.run] if args.run else list(PAPER_RUNS)
        check_finite_range("--workers", args.workers, 1)
        for pile, rate, seconds, _ in runs:  # refuse a bad run before any DEM starts
            check_run(design, pile, rate, seconds, field="--run")
        if args.model is not None:  # and a bad model file, once, not once per worker
            from surrogate.rom.model import RomModel
            RomModel.load(args.model)
        calls = [(_task, {"design": args.design, "pile": pile, "rate": rate,
                          "seconds": seconds, "seed": seed, "model": args.model})
                 for pile, rate, seconds, seed in runs]
        progress(f"landing: {len(calls)} measurements on {args.workers} workers")
        with batch.LocalExecutor(args.workers) as executor:
            measurements = batch.run_calls(calls, executor)
    except (ValidationError, OSError, batch.TaskFailed) as error:
        print(f"landing: error: {error}", file=sys.stderr)
        return 2
    result = {"design": args.design, "measurements": measurements, **summary(measurements)}
    args.out.mkdir(parents=True, exist_ok=True)
    jsonio.write(args.out / "landing.json", result, indent=1)
    for m in measurements:
        print(_line(m))
    s = result["extra_spread_m"]
    print(f"extra spread over {s['n']} measurements: mean {s['mean']:.2f} m, sd {s['std']:.2f} m "
          f"({s['min']:.2f}-{s['max']:.2f})")
    return 0


def _task(design: str, pile: str, rate: float, seconds: int, seed: int, model=None) -> dict:
    from surrogate.rom import paper_design as pd

    return measure(pd.get_design(design), pile, rate, seconds, seed, model,
                   progress=lambda message: print(message, file=sys.stderr, flush=True))


if __name__ == "__main__":
    sys.exit(main())
