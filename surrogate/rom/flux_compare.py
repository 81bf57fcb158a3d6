"""Velocity fit against mass-flux fit on the training design, run by run.

Source: the diagnosis in surrogate/rom/README.md ("What limits the accuracy
now"): on the 2 t/s scene the fitted field's upper funnel core is too slow
and the flux it carries down through a row is not the feeder's. This module
measures the same two things by leave-one-run-out cross-validation on the
training design only (no held-out scene enters): each run's states are
predicted by a model fitted on the other runs (``RomModel``, ``target``
"velocity" or "flux", the same POD + ridge regression; the flux model's
velocity is its flux over the run's DEM cell mass, floored, as the storage
uses it at the ROM's mass).

Quantities (per run discharging at least ``kinematic.LEAST_DISCHARGE`` =
100 kg/s, time means over its states):

- axis speed [m/s]: the time-mean downward speed -v_y of the cells within
  ``kinematic.AXIS_HALF_WIDTH`` = 3 m of the outlet, in the rows whose axis
  cells are bulk (DEM fill >= ``kinematic.BULK_FILL`` = 0.7) in at least 90 %
  of the states; reported as the RMS difference from the DEM's over those
  cells, and the mean over the upper half of those rows (the "upper core").
- row flux [m^2/s]: Phi_j = sum_i (M_ij / M_full) (-v_y,ij) dx, the downward
  flux through row j with the DEM's cell fill as weight (M_full = rho_A dx dy),
  time-mean; reported as the RMS difference from the DEM's over the same rows
  and, for scale, the discharge's q_out / rho_A.
- field error: ``metrics.velocity_field_rel_error`` of the run's states (the
  model selection's criterion).

Parameters: ``velocity`` and ``flux`` are (mass modes, velocity modes, ridge)
and (mass modes, flux modes, ridge, flux floor) [-]; the defaults are what
the selections chose on the paper design (velocity: the shipped model,
4/4/100; flux: ``minetwin rom train --target flux``'s choice).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from cosim import jsonio
from surrogate.rom import doe, metrics
from surrogate.rom.grid import Grid
from surrogate.rom.kinematic import AXIS_HALF_WIDTH, BULK_FILL, LEAST_DISCHARGE
from surrogate.rom.model import RomModel


def rms(values) -> float:
    """Root mean square of ``values`` (0 for none)."""
    values = np.asarray(values, dtype=np.float64).ravel()
    return float(np.linalg.norm(values) / max(values.size, 1) ** 0.5)


def _funnel_design(directory) -> tuple:
    """``(grid, container, samples, run names, axis, full)`` of a design folder:
    ``doe.training_runs``, the columns within ``AXIS_HALF_WIDTH`` of the outlet
    (nx,) and the mass of a full cell [kg]."""
    grid, container, samples, names = doe.training_runs(directory)
    x, _ = grid.centres()
    axis = np.abs(x - container.outlet_x) <= AXIS_HALF_WIDTH
    return grid, container, samples, names, axis, container.full_cell_mass(grid)


def _core_rows(mass: np.ndarray, full: float, axis: np.ndarray) -> list[int]:
    """Rows whose axis cells are at least ``BULK_FILL`` full in 90 % of the samples
    ``mass`` (S, ny, nx) [kg] (``kinematic.compare_on_design``'s rule)."""
    kept = (mass >= BULK_FILL * full).mean(0) >= 0.9
    return [j for j in range(mass.shape[1]) if kept[j, axis].all()]


def _discharging_runs(samples: dict, names: list[str]):
    """``(name, held, used)`` per run: the run's sample rows, and those of them
    discharging at least ``LEAST_DISCHARGE``; runs with none are left out."""
    for number, name in enumerate(names):
        held = samples["run"] == number
        used = held & (samples["discharge_rate"] >= LEAST_DISCHARGE)
        if used.any():
            yield name, held, used


def compare(directory, velocity=(4, 4, 100.0), flux=(4, 4, 100.0, 0.5)) -> dict:
    """``{run name: {...}}``: the module docstring's quantities for the DEM, the
    velocity fit and the flux fit, each fitted without the run."""
    grid, container, samples, names, axis, full = _funnel_design(directory)
    _, y = grid.centres()
    out = {}
    for name, held, used in _discharging_runs(samples, names):
        models = {
            "velocity": RomModel(grid, *velocity, container),
            "flux": RomModel(grid, *flux[:3], container, target="flux", flux_floor=flux[3]),
        }
        for model in models.values():
            model.fit(samples["mass"][~held], samples["discharge_rate"][~held],
                      samples["inflow_rate"][~held], samples["velocity"][~held])
        mass = samples["mass"][used].astype(np.float64)
        rates = samples["discharge_rate"][used].astype(np.float64)
        fields = {"dem": samples["velocity"][used].astype(np.float64)}
        for key, model in models.items():
            fields[key] = np.array([model.predict(m, q, i, check=False) for m, q, i in
                                    zip(mass, rates, samples["inflow_rate"][used])])
        rows = _core_rows(mass, full, axis)
        upper = rows[len(rows) // 2:]
        speed = {k: -f[..., 1].mean(0) for k, f in fields.items()}
        row_flux = {k: (-(mass / full) * f[..., 1]).mean(0).sum(1) * grid.dx
                    for k, f in fields.items()}
        entry = {"samples": int(used.sum()), "discharge_rate": float(rates.mean()),
                 "q_over_rho": float(rates.mean() / container.areal_density),
                 "rows": [float(y[j]) for j in rows],
                 "upper_axis_speed": {k: float(s[upper][:, axis].mean()) if upper else None
                                      for k, s in speed.items()},
                 "row_flux": {k: [float(f[j]) for j in rows] for k, f in row_flux.items()}}
        for key in models:
            entry[key] = {
                "axis_speed_rms": rms(speed[key][rows][:, axis] - speed["dem"][rows][:, axis]),
                "row_flux_rms": rms(row_flux[key][rows] - row_flux["dem"][rows]),
                "field_rel_error": metrics.velocity_field_rel_error(
                    fields[key], fields["dem"], mass)}
        out[name] = entry
    return out


def projection_ceiling(directory, modes=(4, 8, 16), flux_floor: float = 0.5) -> dict:
    """``{run name: {"velocity"|"flux": {modes: (upper-core axis speed, top-row
    flux)}}}`` plus the DEM's (``"dem"``): each run's DEM field projected onto
    the first ``modes`` POD modes of the other runs' velocity (uncentred) or flux
    (the flux then over the DEM cell mass floored at ``flux_floor`` full cells):
    what a fit with that many modes could at best reproduce (same rows and
    cells as ``compare``)."""
    from surrogate.rom.model import flux_samples, pod_basis

    grid, container, samples, names, axis, full = _funnel_design(directory)
    shape = (-1, grid.ny, grid.nx, 2)
    out = {}
    for name, held, used in _discharging_runs(samples, names):
        mass = samples["mass"][used].astype(np.float64)
        rows = _core_rows(mass, full, axis)
        upper = rows[len(rows) // 2:]

        def summary(field):
            speed = -field[..., 1].mean(0)
            row = (-(mass / full) * field[..., 1]).mean(0).sum(1) * grid.dx
            return float(speed[upper][:, axis].mean()), float(row[rows[-1]])

        dem = samples["velocity"][used].astype(np.float64)
        entry = {"dem": summary(dem)}
        divisor = np.maximum(mass, flux_floor * full)[..., None]
        for target in ("velocity", "flux"):
            train = samples["velocity"][~held]
            here = dem.reshape(len(dem), -1)
            if target == "flux":
                train = flux_samples(samples["mass"][~held], train)
                here = flux_samples(mass, dem)
            _, _, vt, _ = pod_basis(train, centred=False)
            entry[target] = {}
            for k in modes:
                projected = ((here @ vt[:k].T) @ vt[:k]).reshape(shape)
                if target == "flux":
                    projected = projected / divisor
                entry[target][k] = summary(projected)
        out[name] = entry
    return out


def _pile(grid: Grid, cells: np.ndarray, pool: np.ndarray, rng) -> tuple:
    """Particles (masses drawn from ``pool`` [kg]) filling the cells of the mass
    field ``cells`` (ny, nx) [kg] cell by cell, uniform within each cell [m]."""
    target = np.asarray(cells, dtype=np.float64).ravel()
    count = int(target.sum() / pool.mean() * 1.3) + 16
    mass = rng.choice(pool, count)
    centre = np.cumsum(mass) - 0.5 * mass
    keep = centre < target.sum()
    mass, centre = mass[keep], centre[keep]
    cell = np.minimum(np.searchsorted(np.cumsum(target), centre, side="right"), target.size - 1)
    row, column = np.divmod(cell, grid.nx)
    position = np.stack([grid.x_min + (column + rng.random(cell.size)) * grid.dx,
                         grid.y_min + (row + rng.random(cell.size)) * grid.dy], axis=1)
    return mass, position


def closed_loop(directory, models: dict, runs=None, seed: int = 0, options=None) -> dict:
    """``{run: {"dem" | model name: {...}}}``: each ``RomStorage`` (default options,
or ``options``, a dict of ``RomStorage`` keyword options, for every model;
    the model files ``models`` {name: path}) started from a training run's first
    mass field (particles drawn from the masses the design's DEM runs discharged),
    every run commanded at least ``LEAST_DISCHARGE``, driven at the
    run's commanded discharge and mean inflow for as many seconds as it was
    sampled, its own fields sampled once per ``doe.CONTROL_STEP``: time-mean
    upper-core axis speed [m/s] of the field the bulk moved by (projected) and of
    the model's prediction at the ROM's mass (before the projection), the ROM's
    upper-core fill [-] and its top-row flux [m^2/s] (rows and cells as in
    ``compare``, fixed by the DEM run), the axis speed row by row and the
    speed and fill of the feeder's row over the opening. Training data only."""
    import warnings

    from cosim.particles import ParticleStore
    from surrogate.rom.storage import RomStorage

    grid, container, samples, names, axis, full = _funnel_design(directory)
    x, _ = grid.centres()
    files = [Path(directory, "train", f"{name}.npz") for name in names]
    pools, setpoints = [], []
    for path in files:
        with np.load(path) as data:
            pools.append(np.asarray(data["out_mass"], dtype=np.float64))
            setpoints.append(float(data["setpoint"][0]))
    pool = np.concatenate(pools)  # every run's discharged masses
    out = {}
    for number, path in enumerate(files):
        setpoint = setpoints[number]
        if (runs is not None and path.stem not in runs) or setpoint < LEAST_DISCHARGE:
            continue
        rows_used = np.flatnonzero(samples["run"] == number)
        mass_dem = samples["mass"][rows_used].astype(np.float64)
        rows = _core_rows(mass_dem, full, axis)
        upper = rows[len(rows) // 2:]
        inflow = float(samples["inflow_rate"][rows_used].mean())
        opening = np.abs(x - container.outlet_x) <= 0.5 * container.outlet_width

        def summary(mass, field):
            speed = -field[..., 1].mean(0)
            row = (-(mass / full) * field[..., 1]).mean(0).sum(1) * grid.dx
            fill = mass.mean(0) / full
            return {"upper_axis_speed": float(speed[upper][:, axis].mean()),
                    "upper_axis_fill": float(fill[upper][:, axis].mean()),
                    "top_row_flux": float(row[rows[-1]]),
                    "axis_speed_by_row": [float(speed[j, axis].mean()) for j in rows],
                    "feeder_row_speed": [float(v) for v in speed[0, opening]],
                    "feeder_row_fill": [float(v) for v in fill[0, opening]]}

        entry = {"dem": summary(mass_dem, samples["velocity"][rows_used].astype(np.float64))}
        for name, model_path in models.items():
            rng = np.random.default_rng(seed)
            model = RomModel.load(model_path)
            mass, position = _pile(grid, mass_dem[0], pool, rng)
            steps = rows_used.size
            fed = rng.choice(pool, int(inflow * steps * doe.CONTROL_STEP / pool.min()) + 1)
            arrival = np.searchsorted(np.cumsum(fed), inflow * doe.CONTROL_STEP
                                      * np.arange(1, steps + 1), side="right")
            store = ParticleStore(capacity=4096)
            ids = store.add(mass=mass, f=doe.FEED_F, grade=np.full(mass.size, 0.01),
                            hardness=np.ones(mass.size), owner=1, time=0.0)
            storage = RomStorage(model, rng=np.random.default_rng(seed), **(options or {}))
            storage.bind(store, 1)
            storage.place(ids, position)
            masses, moved, predicted, first = [], [], [], 0
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                for k in range(steps):
                    t = k * doe.CONTROL_STEP
                    if arrival[k] > first:
                        count = arrival[k] - first
                        new = store.add(mass=fed[first:arrival[k]], f=doe.FEED_F,
                                        grade=np.full(count, 0.01), hardness=np.ones(count),
                                        owner=1, time=t)
                        storage.receive(new, t)
                        first = arrival[k]
                    leaving = storage.step(t, doe.CONTROL_STEP, setpoint)
                    store.remove_slots(store.slots(leaving))
                    fields = storage.fields()
                    masses.append(fields["mass"])
                    moved.append(np.array(fields["velocity"], dtype=np.float64))
                    predicted.append(storage.predicted_field(fields["mass"], setpoint, inflow))
            masses = np.array(masses)
            entry[name] = {**summary(masses, np.array(moved)),
                           "predicted": summary(masses, np.array(predicted))}
        out[path.stem] = entry
    return out


def _cell(value, digits: int) -> str:
    """``value`` for a table, "-" where a run has none (no full rows on the axis)."""
    return "-" if value is None or value != value else f"{value:.{digits}f}"


def table(report: dict) -> str:
    """The comparison as a Markdown table (velocity fit / flux fit per column)."""
    lines = ["| run | q_out [kg/s] | axis speed RMS error [m/s] | upper-core axis speed "
             "DEM / vel / flux [m/s] | row flux RMS error [m^2/s] (q/rho_A) | row flux in the "
             "top axis row DEM / vel / flux [m^2/s] | field error |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, e in report.items():
        up = e["upper_axis_speed"]
        top = {k: v[-1] if v else None for k, v in e["row_flux"].items()}
        lines.append(
            f"| {name} | {e['discharge_rate']:.0f} | {_cell(e['velocity']['axis_speed_rms'], 3)}"
            f" / {_cell(e['flux']['axis_speed_rms'], 3)} | {_cell(up['dem'], 3)} / "
            f"{_cell(up['velocity'], 3)} / {_cell(up['flux'], 3)} | "
            f"{_cell(e['velocity']['row_flux_rms'], 2)} / {_cell(e['flux']['row_flux_rms'], 2)}"
            f" ({e['q_over_rho']:.2f}) | {_cell(top['dem'], 2)} / {_cell(top['velocity'], 2)} / "
            f"{_cell(top['flux'], 2)} | {e['velocity']['field_rel_error']:.3f} / "
            f"{e['flux']['field_rel_error']:.3f} |")
    return "\n".join(lines)


def fit_options(count: int, names: str):
    """An argparse type: ``count`` comma-separated numbers (``names``)."""
    def parse(text: str) -> tuple:
        try:
            values = [float(part) for part in text.split(",")]
        except ValueError:
            values = []
        if len(values) != count or not all(v >= 0 for v in values):
            raise argparse.ArgumentTypeError(f"must be {count} numbers >= 0: {names} "
                                             f"(got {text!r})")
        return (int(values[0]), int(values[1]), *values[2:])
    return parse


def design_parser(description: str) -> argparse.ArgumentParser:
    """The diagnostics' common options: ``--data``, ``--flux``, ``--json``."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--data", required=True, help="design folder (doe.json, train/*.npz)")
    parser.add_argument("--flux", default="4,4,100,0.5",
                        type=fit_options(4, "mass modes, flux modes, ridge, flux floor"),
                        help="flux fit: mass modes, flux modes, ridge, flux floor (4,4,100,0.5)")
    parser.add_argument("--json", default=None, help="also write the report here")
    return parser


def design_missing(args, prog: str) -> bool:
    """Whether ``--data`` is not a design folder (said on stderr)."""
    if (Path(args.data) / "doe.json").is_file():
        return False
    print(f"{prog}: error: --data: must be a design folder with doe.json (got {args.data})",
          file=sys.stderr)
    return True


def main(argv=None) -> int:
    parser = design_parser("Velocity fit against mass-flux fit on a training design, leave "
                           "one run out (surrogate.rom.flux_compare)")
    parser.add_argument("--velocity", default="4,4,100",
                        type=fit_options(3, "mass modes, velocity modes, ridge"),
                        help="velocity fit: mass modes, velocity modes, ridge (4,4,100)")
    parser.add_argument("--ceiling", action="store_true",
                        help="instead: the DEM fields projected onto 4, 8 and 16 POD modes "
                             "of the other runs (projection_ceiling), as JSON")
    parser.add_argument("--closed-loop", metavar="NAME=MODEL,...", default=None,
                        help="instead: run the ROM with these model files through the "
                             "training runs (closed_loop), as JSON")
    parser.add_argument("--runs", default=None,
                        help="with --closed-loop: run names, comma-separated")
    parser.add_argument("--packing-density", type=float, default=None, metavar="KG_M2",
                        help="with --closed-loop: RomStorage's packing_density [kg/m^2]")
    args = parser.parse_args(argv)
    if design_missing(args, "flux_compare"):
        return 2
    if args.ceiling:
        print(jsonio.dumps(projection_ceiling(args.data), indent=1))
        return 0
    if args.closed_loop:
        names = dict(item.split("=", 1) for item in args.closed_loop.split(","))
        options = ({} if args.packing_density is None
                   else {"packing_density": args.packing_density})
        print(jsonio.dumps(closed_loop(args.data, names, args.runs.split(",") if args.runs
                                       else None, options=options), indent=1))
        return 0
    report = compare(args.data, args.velocity, args.flux)
    if args.json:
        jsonio.write(args.json, report, indent=1)
    print(table(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
