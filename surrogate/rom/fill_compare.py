"""The flux fit's fitted fill on the training design, run by run (leave one run out).

Source: the diagnosis in surrogate/rom/README.md ("Mass-flux fit"): the DEM's
flowing cells over the feeder are looser than the ROM packs them, so the DEM's
flux over the ROM's cell mass is too low a speed. ``RomModel(target="flux",
fill_law="dem")`` divides the flux by no more than a fill fitted on the
training DEM (``surrogate.rom.model``, "Fitted fill"). This module measures, by
leave-one-run-out cross-validation on the training design only (no held-out
scene enters), per run discharging at least ``kinematic.LEAST_DISCHARGE`` =
100 kg/s, over its discharging states (time means):

- fill [-] = M / M_full (M_full = rho_A dx dy) in the feeder's cells (bottom
  row over the opening, ``model.feeder_cells``) and in the funnel above them
  (rows 2-8 m up, cells over the opening, covered ones only,
  ``model.covered_cells``): the DEM's, the law's at the DEM's own flux
  (phi(|F_DEM| / M_full), the law alone) and the law's at the model's
  predicted flux (what the option divides by at the DEM's states, before the
  min with the ROM's own mass);
- the law's RMS error over all the run's covered cells against the DEM's
  fill, next to two laws without a parameter per flux: the ROM's packing
  (fill 1) and the training runs' mean fill of covered cells;
- downward speed [m/s] in the same cells at a ROM-like packing (every covered
  cell of the DEM's mass field set to a full cell, the others kept): the
  DEM's own speed, the flux fit's without and with the law;
- field error: ``metrics.velocity_field_rel_error`` at the DEM's mass (the
  selection's criterion), without and with the law.

Parameters: ``flux`` = (mass modes, flux modes, ridge, flux floor) [-]
(default 4, 4, 100, 0.5: the flux selection's choice on the paper design).
"""

from __future__ import annotations

import sys

import numpy as np

from cosim import jsonio
from surrogate.rom import doe, metrics
from surrogate.rom.flux_compare import design_missing, design_parser, rms
from surrogate.rom.kinematic import LEAST_DISCHARGE
from surrogate.rom.model import (RomModel, covered_cells, feeder_cells, fill_law,
                                 fill_law_tables, flux_samples)

FUNNEL_ROWS = (2.0, 8.0)
"""Heights [m] above the floor between which cell centres count as the funnel."""


def compare(directory, flux=(4, 4, 100.0, 0.5)) -> dict:
    """``{run name: {...}}``: the module docstring's quantities, each model and
    law fitted without the run."""
    grid, container, samples, names = doe.training_runs(directory)
    x, y = grid.centres()
    full = container.full_cell_mass(grid)
    feeder = feeder_cells(grid, container)
    opening = feeder[0]
    funnel = np.zeros_like(feeder)
    height = y - container.floor
    funnel[(height >= FUNNEL_ROWS[0]) & (height <= FUNNEL_ROWS[1])] = True
    funnel &= opening[None, :]
    mass_all = samples["mass"].astype(np.float64)
    velocity_all = samples["velocity"].astype(np.float64)
    flux_all = flux_samples(mass_all, velocity_all).reshape(velocity_all.shape)
    covered_all = covered_cells(mass_all, full)
    out = {}
    for number, name in enumerate(names):
        held = samples["run"] == number
        used = held & (samples["discharge_rate"] >= LEAST_DISCHARGE)
        if not used.any():
            continue
        options = dict(container=container, target="flux", flux_floor=flux[3])
        models = {law: RomModel(grid, *flux[:3], fill_law=law, **options).fit(
            mass_all[~held], samples["discharge_rate"][~held], samples["inflow_rate"][~held],
            velocity_all[~held]) for law in (None, "dem")}
        tables = fill_law_tables(mass_all[~held], flux_all[~held], feeder, full)
        mass, velocity = mass_all[used], velocity_all[used]
        rates, inflow = samples["discharge_rate"][used], samples["inflow_rate"][used]
        covered = covered_all[used]
        fill = mass / full
        j_dem = np.sqrt((flux_all[used] ** 2).sum(-1)) / full
        law_dem = fill_law(tables, j_dem, feeder)
        predicted_flux = np.array([models["dem"].predict_flux(m, q, i, check=False)
                                   for m, q, i in zip(mass, rates, inflow)])
        law_predicted = fill_law(tables, np.sqrt((predicted_flux ** 2).sum(-1)) / full, feeder)
        mean_fill = float((mass_all[~held] / full)[covered_all[~held]].mean())
        packed = np.where(covered, full, mass)  # a ROM-like packing of the DEM's states
        feeder_used = covered & feeder[None]
        funnel_used = covered & funnel[None]

        def in_cells(values, cells):
            return float(values[cells].mean()) if cells.any() else float("nan")

        speeds = {"dem": -velocity[..., 1]}
        fields = {}
        for law, model in models.items():
            key = "flux" if law is None else "flux_fill"
            speeds[key] = np.array([-model.predict(m, q, i, check=False)[..., 1]
                                    for m, q, i in zip(packed, rates, inflow)])
            fields[key] = metrics.velocity_field_rel_error(
                np.array([model.predict(m, q, i, check=False)
                          for m, q, i in zip(mass, rates, inflow)]), velocity, mass)
        out[name] = {
            "samples": int(used.sum()), "discharge_rate": float(rates.mean()),
            "feeder_fill": {"dem": in_cells(fill, feeder_used),
                            "law_at_dem_flux": in_cells(law_dem, feeder_used),
                            "law_at_predicted_flux": in_cells(law_predicted, feeder_used)},
            "funnel_fill": {"dem": in_cells(fill, funnel_used),
                            "law_at_dem_flux": in_cells(law_dem, funnel_used),
                            "law_at_predicted_flux": in_cells(law_predicted, funnel_used)},
            "covered_fill_rms_error": {"law": rms((law_dem - fill)[covered]),
                                       "full_cell": rms((1.0 - fill)[covered]),
                                       "training_mean": rms((mean_fill - fill)[covered])},
            "feeder_speed": {k: in_cells(v, feeder_used) for k, v in speeds.items()},
            "funnel_speed": {k: in_cells(v, funnel_used) for k, v in speeds.items()},
            "field_rel_error": fields}
    return out


def table(report: dict) -> str:
    """The comparison as a Markdown table."""
    lines = ["| run | q_out [kg/s] | feeder fill DEM / law (DEM flux) / law (fitted flux) | "
             "funnel fill DEM / law / law | covered-cell fill RMS error law / full / mean | "
             "feeder speed at ROM packing DEM / flux / flux+fill [m/s] | funnel speed "
             "DEM / flux / flux+fill [m/s] | field error flux / flux+fill |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, e in report.items():
        f, u, r = e["feeder_fill"], e["funnel_fill"], e["covered_fill_rms_error"]
        s, w, fe = e["feeder_speed"], e["funnel_speed"], e["field_rel_error"]
        lines.append(
            f"| {name} | {e['discharge_rate']:.0f} | {f['dem']:.3f} / {f['law_at_dem_flux']:.3f}"
            f" / {f['law_at_predicted_flux']:.3f} | {u['dem']:.3f} / {u['law_at_dem_flux']:.3f}"
            f" / {u['law_at_predicted_flux']:.3f} | {r['law']:.3f} / {r['full_cell']:.3f} / "
            f"{r['training_mean']:.3f} | {s['dem']:.3f} / {s['flux']:.3f} / "
            f"{s['flux_fill']:.3f} | {w['dem']:.3f} / {w['flux']:.3f} / {w['flux_fill']:.3f} | "
            f"{fe['flux']:.3f} / {fe['flux_fill']:.3f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = design_parser("The flux fit's fitted fill on a training design, leave one run "
                           "out (surrogate.rom.fill_compare)")
    args = parser.parse_args(argv)
    if design_missing(args, "fill_compare"):
        return 2
    report = compare(args.data, args.flux)
    if args.json:
        jsonio.write(args.json, report, indent=1)
    print(table(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
