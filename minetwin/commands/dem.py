"""``minetwin dem``: build a DEM stockpile and discharge it.

``minetwin dem pile --particles N --out DIR`` pours a pile from the inlets
(or, with ``--method pack``, lays a pile out on a lattice and lets it settle)
and writes ``DIR/checkpoint.npz``, ``DIR/summary.json`` and pictures
``DIR/pile_{grade,residence_time,speed}.png``.

``minetwin dem discharge --from DIR --rate KG_PER_S --duration S --out DIR``
continues from ``DIR/checkpoint.npz`` with the feeder at the given rate and
writes the same outputs plus ``DIR/discharged.csv`` (one row per particle
that left).
"""

from __future__ import annotations

import sys

from cosim import jsonio

def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "dem", help="2D DEM of the stockpile: build a pile, discharge it",
        description="Numba 2D DEM of the stockpile (surrogate/dem/README.md).")
    sub = parser.add_subparsers(dest="dem_command", metavar="ACTION")
    pile = sub.add_parser("pile", help="fill a pile from the inlets and let it settle",
                          description="Fill a pile of N particles from the two inlets "
                                      "(lots alternate between them) and let it settle.")
    pile.add_argument("--particles", type=int, required=True, help="number of particles N")
    pile.add_argument("--out", required=True, help="output directory")
    pile.add_argument("--config", help="TOML file with DemConfig fields (top level or [dem])")
    pile.add_argument("--method", choices=("pour", "pack"), default="pour",
                      help="pour from the inlets (default) or pack on a lattice and settle")
    pile.add_argument("--lot-kg", type=float, default=600.0,
                      help="mass per emitted lot [kg] (600)")
    pile.add_argument("--lot-interval", type=float, default=0.5,
                      help="time between lots [s] (0.5, i.e. 1.2 t/s)")
    pile.add_argument("--settle-time", type=float, default=20.0,
                      help="longest settling time after filling [s] (20)")
    pile.add_argument("--snapshot-interval", type=float,
                      help="write snapshots to OUT/snapshots every this many seconds")
    pile.add_argument("--seed", type=int, default=0, help="random seed (0)")
    pile.set_defaults(handler=_stopping_on_blow_up(run_pile))

    dis = sub.add_parser("discharge", help="discharge a pile through the feeder",
                         description="Continue from a pile's checkpoint with the feeder of "
                                     "outlet 0 at a constant rate, optionally under changed "
                                     "DEM settings (--set).")
    dis.add_argument("--from", dest="source", required=True,
                     help="directory with checkpoint.npz (from `dem pile` or `dem discharge`) "
                          "or a checkpoint .npz file (e.g. a design's states/run_<key>.npz)")
    dis.add_argument("--set", dest="changes", action="append", default=[],
                     metavar="FIELD=VALUE",
                     help="continue under this DemConfig field changed, e.g. method=explicit, "
                          "solver_iterations=200, rolling_resistance=0.3 (repeatable; the "
                          "contact history is cleared and the new setting's default step used)")
    dis.add_argument("--rate", type=float, required=True,
                     help="feeder setpoint [kg/s] (0..2000; capped at what the opening passes, "
                          "Beverloo)")
    dis.add_argument("--duration", type=float, required=True, help="simulated time [s]")
    dis.add_argument("--out", required=True, help="output directory")
    dis.add_argument("--snapshot-interval", type=float,
                     help="write snapshots to OUT/snapshots every this many seconds")
    dis.set_defaults(handler=_stopping_on_blow_up(run_discharge))
    parser.set_defaults(handler=lambda args: (parser.print_help(sys.stderr), 2)[1])


def _stopping_on_blow_up(handler):
    """``handler`` with a DEM blow-up (``DemBlowUp``: what, when, why) reported
    on stderr and exit code 1 instead of a traceback."""

    def guarded(args):
        from surrogate.dem import DemBlowUp

        try:
            return handler(args)
        except DemBlowUp as exc:
            print(f"minetwin dem {args.dem_command}: error: {exc}", file=sys.stderr)
            return 1

    return guarded


def _check_positive(name, value, allow_zero=False):
    import math

    from cosim.errors import ValidationError

    if not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise ValidationError(name, ">= 0" if allow_zero else "> 0", f"got {value!r}")


def _finish(dem, out, label, wall, steps, counter, discharged_kg, balance):
    """Write checkpoint, pictures and summary.json; print the summary (``counter``:
    the command's ``_Counter``); warn on stderr when the nonsmooth solver did not
    converge."""

    from surrogate.dem.analysis import angle_of_repose
    from surrogate.dem.plots import pile_pictures

    dem.save_checkpoint(out / "checkpoint.npz")
    pile_pictures(dem.snapshot(), out, run=label)
    summary = {
        "particles": dem.n,
        "dt_s": dem.dt,
        "steps": steps,
        "wall_s": wall,
        "particle_steps_per_s": counter.particle_steps / wall if wall > 0 else 0.0,
        "angle_of_repose_deg": angle_of_repose(dem.pos, dem.radius),
        "discharged_kg": discharged_kg,
        "mass_balance_rel_error": balance,
        "held_kg": dem.held_mass(),
        "time_s": dem.time,
        "stable_dt_s": dem.stable_dt,
        "max_overlap_over_diameter": dem.max_overlap_ratio(),
        "list_builds": dem.list_builds,
    }
    if dem.nonsmooth:
        from surrogate.dem.nonsmooth import RESIDUAL_WARNING, convergence

        solver = summary["solver"] = convergence(dem.solver_stats, counter.solver_stats, dem.dt,
                                                 dem.cfg)
        if solver["converged"] is False:
            print(f"{counter.command}: warning: the nonsmooth solver did not converge: its "
                  f"last sweep still changed a velocity by "
                  f"{solver['mean_last_sweep_change_m_s']:.3g} m/s on average, more than "
                  f"{RESIDUAL_WARNING:g} g h = {solver['residual_limit_m_s']:.3g} m/s, so the "
                  f"pile creeps instead of resting; more sweeps (solver_iterations, now "
                  f"{solver['solver_iterations']}) or softer contacts (normal_stiffness) help "
                  f"(surrogate/dem/README.md, \"Solver convergence\")", file=sys.stderr)
    jsonio.write(out / "summary.json", summary, indent=2)
    print(jsonio.dumps(summary, indent=2))
    return 0


COMPILE_NOTE = ("the first steps compile the DEM kernels (numba, cached for later runs): "
                "up to about a minute without progress lines")


class _Counter:
    """Progress callback (``cosim.progress``: simulated seconds since the command
    started, of ``duration`` [s]; particles, steps, held mass) that also counts
    particle-steps between calls."""

    def __init__(self, label: str, duration: float, dem):
        from cosim.progress import Progress

        # a continued state starts at its own time: count from there
        self.t0 = dem.time
        self.command = label
        self.lines = Progress(label, duration, every_s=2.0)
        self.lines.note(COMPILE_NOTE)
        self.steps = dem.steps_done
        self.particle_steps = 0.0
        self.writer = None
        self.solver_stats = dem.solver_stats.copy()

    def __call__(self, dem):
        self.particle_steps += dem.n * (dem.steps_done - self.steps)
        self.steps = dem.steps_done
        if self.writer is not None:
            self.writer.maybe_write(dem)
        self.lines.update(dem.time - self.t0, self.state(dem))

    def close(self, dem) -> None:
        """The final line, with the end time and the wall time it took."""
        self.lines.update(dem.time - self.t0, self.state(dem))
        self.lines.close(self.state(dem))

    @staticmethod
    def state(dem) -> str:
        return f"{dem.n} particles, step {dem.steps_done}, held {dem.held_mass() / 1e3:.1f} t"


def run_pile(args) -> int:
    import math
    import time
    from pathlib import Path

    from cosim.errors import ValidationError
    from surrogate.dem import DemConfig
    from surrogate.dem.builders import (
        config_for_particles,
        packed_pile,
        pour_pile,
        settle,
    )
    from surrogate.dem.simulation import Dem
    from surrogate.dem.snapshots import SnapshotWriter

    if args.particles < 1 or args.particles > 200_000:
        raise ValidationError("--particles", "in [1, 200000]", f"got {args.particles}")
    _check_positive("--lot-kg", args.lot_kg)
    _check_positive("--lot-interval", args.lot_interval)
    _check_positive("--settle-time", args.settle_time, allow_zero=True)
    base = DemConfig.from_toml(args.config) if args.config else None
    cfg = base if base is not None else config_for_particles(args.particles)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    if args.method == "pour":
        dem = Dem(cfg, seed=args.seed)
    else:
        dem = packed_pile(cfg, args.particles, seed=args.seed)
    from surrogate.dem.emitter import mean_particle_mass

    # the expected end: the fill (its lots estimated from the mean particle mass),
    # then the whole settling time (settling may stop earlier)
    lots = math.ceil(args.particles * mean_particle_mass(cfg) / args.lot_kg)
    longest = (lots * args.lot_interval if args.method == "pour" else 0.0) + args.settle_time
    counter = _Counter("dem pile", longest, dem)
    if args.snapshot_interval:
        counter.writer = SnapshotWriter(out / "snapshots", args.snapshot_interval)
    if args.method == "pour":
        pour_pile(dem, args.particles, lot_kg=args.lot_kg, lot_interval=args.lot_interval,
                  progress=counter)
    settle(dem, max_time=args.settle_time, progress=counter)
    counter.close(dem)
    wall = time.perf_counter() - start
    from cosim.plotstyle import run_label

    label = run_label(scenario=f"dem pile ({args.method}, {args.particles} particles)",
                      seed=args.seed, model="dem")
    return _finish(dem, out, label, wall, dem.steps_done, counter, dem.discharged_mass,
                   dem.mass_balance_error())


def run_discharge(args) -> int:
    import time
    from pathlib import Path

    from cosim.errors import ValidationError
    from surrogate.dem.simulation import Dem
    from surrogate.dem.snapshots import SnapshotWriter

    source = Path(args.source)
    if not source.suffix == ".npz":
        source = source / "checkpoint.npz"
    if not source.is_file():
        raise ValidationError("--from", "a directory holding checkpoint.npz or a checkpoint "
                              ".npz file", f"{source} not found")
    _check_positive("--duration", args.duration)
    changes = setting_changes(args.changes)
    dem = Dem.load_checkpoint(source, changes=changes or None)
    dem.set_discharge_rate(args.rate, outlet=0)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    held0 = dem.held_mass()
    steps0 = dem.steps_done
    counter = _Counter("dem discharge", args.duration, dem)
    if args.snapshot_interval:
        counter.writer = SnapshotWriter(out / "snapshots", args.snapshot_interval)
    chunk = 0.25
    end = dem.time + args.duration
    records = []
    start = time.perf_counter()
    while dem.time < end - 1e-9:
        dem.advance(min(chunk, end - dem.time))
        records.append(dem.discharged())
        counter(dem)
    counter.close(dem)
    wall = time.perf_counter() - start
    _write_discharged(out / "discharged.csv", records)
    discharged = float(sum(r["mass"].sum() for r in records))
    balance = abs(held0 - dem.held_mass() - discharged) / held0 if held0 > 0 else 0.0
    rate = discharged / args.duration
    print(f"dem discharge: {discharged:.0f} kg in {args.duration:g} s = {rate:.1f} kg/s "
          f"(setpoint {args.rate:g} kg/s)", file=sys.stderr)
    from cosim.plotstyle import run_label

    label = run_label(scenario=f"dem discharge from {args.source} at {args.rate:g} kg/s",
                      model="dem")
    return _finish(dem, out, label, wall, dem.steps_done - steps0, counter, discharged,
                   balance)


def setting_changes(items: list[str]) -> dict:
    """``--set FIELD=VALUE`` items as DemConfig fields; a value is read as JSON (numbers,
    true/false, lists) and else kept as text (``method=explicit``). Unknown fields
    and bad values are refused by ``DemConfig`` itself, by name."""
    import json

    from cosim.errors import ValidationError

    changes = {}
    for item in items:
        field, sep, text = item.partition("=")
        if not sep or not field.strip():
            raise ValidationError("--set", "FIELD=VALUE", f"got {item!r}")
        try:
            value = json.loads(text)
        except ValueError:
            value = text
        changes[field.strip()] = value
    return changes


def _write_discharged(path, records) -> None:
    import numpy as np
    import pandas as pd

    keys = ("id", "tracking_id", "mass", "grade", "hardness", "entry_time", "time", "outlet")
    frame = pd.DataFrame({k: np.concatenate([r[k] for r in records]) if records else []
                          for k in keys})
    frame.rename(columns={"mass": "mass_kg", "time": "time_s", "entry_time": "entry_time_s"}
                 ).to_csv(path, index=False)
