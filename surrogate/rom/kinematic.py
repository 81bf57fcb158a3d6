"""Kinematic model of the funnel flow above the feeder.

Source: Nedderman and Tuzun (1979), "A kinematic model for the flow of
granular materials", Powder Technology 22, 243-253 (also Nedderman 1992,
"Statics and kinematics of granular materials", chapter 10): in slow flow
towards an outlet, the horizontal velocity u is proportional to the
horizontal gradient of the downward velocity w, u = B dw/dx, and continuity
then gives the diffusion equation dw/dh = B d2w/dx2 in the height h above
the outlet, with B the kinematic (diffusion) length, of the order of a few
particle diameters.

Equations (2-D plane, x horizontal, y up; the outlet a narrow slot at
``Container.outlet_x`` on the floor ``Container.floor``; the settled bulk of
areal density rho_A [kg/m^2]):

- the outlet draws the volume flux Q' = q_out / rho_A [m^2/s] (q_out the
  discharge rate [kg/s]);
- w(x, h) = Q' / sqrt(4 pi B h) exp(-(x - x_o)^2 / (4 B h)) [m/s, down
  positive] at height h = y - floor > 0 [m], the point-source solution, so
  the integral of w over x is Q' at every height;
- u(x, h) = B dw/dx = -(x - x_o) w / (2 h) [m/s]: du/dx = dw/dh, so the
  field (u, -w) is divergence free;
- the field does not depend on the pile's shape or on the inflow (the
  free surface and the inflow are the surface layer's and the packing's
  business); it vanishes when nothing is discharged.

Parameter: the diffusion length B [m] (default ``DIFFUSION_LENGTH``, fitted
by ``fit_diffusion_length`` on the paper-scale training design; the numbers
and the command are in surrogate/rom/README.md, "What limits the accuracy
now").
"""

from __future__ import annotations

import math

import numba
import numpy as np

DIFFUSION_LENGTH = 1.06
"""Kinematic diffusion length B [m]: the least-squares fit of the kinematic field to
the DEM's velocity in the bulk of the paper-scale training design's discharging
samples (``python -m surrogate.rom.kinematic --data surrogate/rom/data/paper_design``;
about 3 mean particle diameters)."""

BULK_FILL = 0.7
"""Least fraction of a full cell's mass (rho_A dx dy) of the cells the fit compares [-]
(the DEM's funnel core dilates to 0.8-0.9 of the settled density)."""

LEAST_DISCHARGE = 100.0
"""Least discharge rate [kg/s] of the samples the fit compares."""


@numba.njit(cache=True)
def _field(x, y, outlet_x, floor, flux, diffusion_length):
    """The kinematic velocity (u, -w) [m/s] at the cell centres ``x`` (nx,),
    ``y`` (ny,) [m]: (ny, nx, 2) (module docstring; 0 at or below the floor)."""
    out = np.zeros((y.size, x.size, 2))
    for j in range(y.size):
        h = y[j] - floor
        if h <= 0.0 or flux == 0.0:
            continue
        spread = 4.0 * diffusion_length * h
        peak = flux / math.sqrt(math.pi * spread)
        for i in range(x.size):
            offset = x[i] - outlet_x
            w = peak * math.exp(-offset * offset / spread)
            out[j, i, 0] = -offset * w / (2.0 * h)
            out[j, i, 1] = -w
    return out


def velocity_field(grid, container, discharge_rate: float,
                   diffusion_length: float = DIFFUSION_LENGTH) -> np.ndarray:
    """The kinematic velocity field [m/s] (ny, nx, 2) at the centres of ``grid``'s
    cells for the feeder's ``discharge_rate`` [kg/s] (module docstring)."""
    x, y = grid.centres()
    flux = float(discharge_rate) / container.areal_density
    return _field(x, y, float(container.outlet_x), float(container.floor), flux,
                  float(diffusion_length))


def hybrid_field(regressed: np.ndarray, kinematic: np.ndarray, grid, container) -> np.ndarray:
    """The hybrid field [m/s] (ny, nx, 2) on ``grid``'s cells: the regression
    ``regressed`` (ny, nx, 2) with its downward speed raised to the kinematic field's
    ``kinematic`` (ny, nx, 2) wherever that is faster, w = max(w_r, w_k), in the
    cells whose centre is higher above ``container``'s floor than its
    ``feeder_zone_height`` [m]; in the feeder's zone, and for the horizontal component
    everywhere, the regression as it is.

    Why (fixed a priori, nothing fitted to the held-out scenes): on the training
    design the kinematic field follows the DEM's time-mean downward speed in the
    funnel's upper core, where the regression is too slow, and is too slow near the
    feeder and off the core, where the regression is right; it has no sideways
    surface flows (surrogate/rom/README.md, "The kinematic field"). Its point-source
    solution grows without bound towards the floor (w ~ 1 / sqrt(h)), while the DEM's
    8 m feeder draws across its opening, so the feeder's zone, where the ROM's feeder
    reads its draw from the field, keeps the regression's. Sources: the regression of
    ``surrogate.rom.model`` and the kinematic model of the module docstring (Nedderman
    and Tuzun 1979); the max is this module's."""
    out = np.array(regressed, dtype=np.float64, copy=True)
    _, y = grid.centres()
    above = y - container.floor > container.feeder_zone_height
    # v = -w: the faster downward speed is the lower v
    out[above, :, 1] = np.minimum(out[above, :, 1], kinematic[above, :, 1])
    return out


def fit_diffusion_length(directory, low: float = 0.1, high: float = 10.0,
                         tolerance: float = 1e-3) -> dict:
    """The diffusion length B [m] whose kinematic field is nearest, in least
    squares over both components, to the DEM's velocity in the bulk cells (at
    least ``BULK_FILL`` full) of the training samples of ``directory`` that
    discharge at least ``LEAST_DISCHARGE``; golden-section search on log B in
    [``low``, ``high``] to a relative ``tolerance``. Returns ``{"diffusion_length",
    "rms_error", "rms_dem"}`` [m, m/s, m/s] (``rms_dem``: the DEM's own RMS speed
    on those cells, the error of a field at rest) and ``"samples"``, ``"cells"``."""
    from surrogate.rom import doe
    from surrogate.rom.container import Container
    from surrogate.rom.grid import Grid

    meta = doe.read_meta(directory)
    grid, container = Grid.from_dict(meta["grid"]), Container.from_dict(meta["container"])
    samples = doe.load_samples(directory)
    used = samples["discharge_rate"] >= LEAST_DISCHARGE
    rates = samples["discharge_rate"][used].astype(np.float64)
    dem = samples["velocity"][used].astype(np.float64)
    bulk = samples["mass"][used] >= BULK_FILL * container.areal_density * grid.dx * grid.dy
    count = int(bulk.sum())

    def mean_square(log_length: float) -> float:
        # the field is linear in the rate: one field per unit rate, scaled per sample
        unit = velocity_field(grid, container, 1.0, math.exp(log_length))
        error = rates[:, None, None, None] * unit[None] - dem
        return float((error ** 2).sum(axis=-1)[bulk].sum() / count)

    ratio = 0.5 * (math.sqrt(5.0) - 1.0)
    a, b = math.log(low), math.log(high)
    c, d = b - ratio * (b - a), a + ratio * (b - a)
    fc, fd = mean_square(c), mean_square(d)
    while b - a > tolerance:
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - ratio * (b - a)
            fc = mean_square(c)
        else:
            a, c, fc = c, d, fd
            d = a + ratio * (b - a)
            fd = mean_square(d)
    best = 0.5 * (a + b)
    return {"diffusion_length": math.exp(best), "rms_error": math.sqrt(mean_square(best)),
            "rms_dem": math.sqrt(float((dem ** 2).sum(axis=-1)[bulk].sum() / count)),
            "samples": int(used.sum()), "cells": count}


AXIS_HALF_WIDTH = 3.0
"""Half-width [m] about the outlet of the funnel's axis in ``compare_on_design``."""


def compare_on_design(directory, model=None, diffusion_length: float = DIFFUSION_LENGTH) -> dict:
    """The kinematic field (and ``model``'s regression, a ``RomModel``, and their
    ``hybrid_field``, if given) against the DEM, run by run, over the training runs
    of ``directory`` that discharge (samples of at least ``LEAST_DISCHARGE``): the time mean of the
    downward speed over the run's cells that are at least ``BULK_FILL`` full in
    90 % of its samples; ``rel_error`` the norm of its difference over those cells
    relative to the DEM's, and ``axis`` its mean over the cells within
    ``AXIS_HALF_WIDTH`` of the outlet per height [m] (rows the core fills)."""
    from surrogate.rom import doe

    grid, container, samples, names = doe.training_runs(directory)
    x, y = grid.centres()
    axis = np.abs(x - container.outlet_x) <= AXIS_HALF_WIDTH
    whole = velocity_field(grid, container, 1.0, diffusion_length)
    unit = whole[..., 1]
    out = {}
    for number, name in enumerate(names):
        used = (samples["run"] == number) & (samples["discharge_rate"] >= LEAST_DISCHARGE)
        if not used.any():
            continue
        mass = samples["mass"][used]
        kept = (mass >= BULK_FILL * container.areal_density * grid.dx * grid.dy).mean(0) >= 0.9
        rates = samples["discharge_rate"][used].astype(np.float64)
        fields = {"dem": -samples["velocity"][used][..., 1].mean(0),
                  "kinematic": -rates.mean() * unit}
        if model is not None:
            regressed = [model.predict(m, q, i, check=False)
                         for m, q, i in zip(mass, rates, samples["inflow_rate"][used])]
            fields["regressed"] = -np.mean([f[..., 1] for f in regressed], axis=0)
            fields["hybrid"] = -np.mean([hybrid_field(f, q * whole, grid, container)[..., 1]
                                         for f, q in zip(regressed, rates)], axis=0)
        rows = [j for j in range(grid.ny) if kept[j, axis].all()]
        scale = float(np.linalg.norm(fields["dem"][kept]))
        out[name] = {"samples": int(used.sum()), "discharge_rate": float(rates.mean()),
                     "height": [float(y[j]) for j in rows],
                     "rel_error": {k: float(np.linalg.norm((f - fields["dem"])[kept]) / scale)
                                   for k, f in fields.items() if k != "dem"},
                     "axis": {k: [float(f[j, axis].mean()) for j in rows]
                              for k, f in fields.items()}}
    return out


if __name__ == "__main__":
    import argparse
    import json

    parser = argparse.ArgumentParser(description="Fit the kinematic diffusion length B to a "
                                                 "DEM training design (surrogate.rom.kinematic)")
    parser.add_argument("--data", required=True, help="design folder (doe.json, train/*.npz)")
    parser.add_argument("--compare", metavar="MODEL", default=None,
                        help="also compare the kinematic field at the default B, this "
                             "ROM file's regression and their hybrid with the DEM, run by run "
                             "(compare_on_design)")
    args = parser.parse_args()
    report = {"fit": fit_diffusion_length(args.data)}
    if args.compare:
        from surrogate.rom.model import RomModel

        report["runs"] = compare_on_design(args.data, RomModel.load(args.compare))
    print(json.dumps(report, indent=1))
