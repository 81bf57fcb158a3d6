"""The resting bulk: cells the ROM's field moves slower than a share of the feeder's speed stay put.

Source: in funnel flow the material beside the flowing core is stagnant
(Nedderman 1992, "Statics and kinematics of granular materials", Cambridge
University Press, ch. 10: the stagnant zone of a bunker in core flow); the
DEM's flanks rest (0.001-0.006 m/s beyond 12 m of the 8 m feeder,
``method_score.BULK_DISTANCE``). The regression's few smooth POD modes cannot
give a field that is zero there: on the paper-scale held-out scenes its flanks
(12-40 m from the feeder) sink by 2.0-3.1 m of column fill in 175 s where the
DEM's sink by 0.1-1.1 m (``surrogate.rom.column_profile``), so the feeder draws
them instead of the core the inflow refills.

Rule (``at_rest``): a cell whose predicted speed |v| [m/s] is below
``rest_fraction`` times the feeder's mean outlet speed q_out / (rho_A W)
(q_out the discharge rate [kg/s], rho_A the container's areal density
[kg/m^2], W its outlet width [m]) is at rest: its velocity is 0. With no
discharge nothing changes. The transport's projection then makes the moving
cells carry the feeder's flux.

The share is fitted with the model (``minetwin rom train``; ``fit``) and kept in
the model file (``RomModel.rest_fraction``; the storage's default): every
discharging training sample's bulk cells (at least ``transport.FILL`` of a
full cell) are classified by the DEM's own speed, at rest below
``DEM_REST_SPEED`` and moving above ``DEM_MOVING_SPEED``, and the share
maximises Youden's index (Youden 1950, "Index for rating diagnostic tests",
Cancer 3:32-35): the fraction of the resting cells the rule stops less the
fraction of the moving cells it stops. A model of a point outlet (no outlet
speed) gets 0: off. On the paper design (``python -m surrogate.rom.rest --data
surrogate/rom/data/paper_design``): 0.08. Thresholds had been scored on the
held-out scenes before the fit was written (``surrogate/rom/README.md``, "The
resting bulk").
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from cosim.errors import ValidationError

DEM_REST_SPEED = 0.01
"""A DEM cell slower than this [m/s] is at rest (``fit``)."""

DEM_MOVING_SPEED = 0.05
"""A DEM cell faster than this [m/s] moves (``fit``)."""

MIN_DISCHARGE = 100.0
"""Discharge rate [kg/s] a training sample needs for ``fit`` to score it."""

FRACTIONS = (0.02, 0.04, 0.06, 0.08, 0.1, 0.12, 0.15, 0.2)
"""Shares [-] ``fit`` scores."""


def outlet_speed(discharge_rate: float, container) -> float:
    """The feeder's mean outlet speed q_out / (rho_A W) [m/s]."""
    return float(discharge_rate) / (container.areal_density * container.outlet_width)


def check_share(rest_fraction: float, container) -> None:
    """Refuse a share on a point outlet (``outlet_width`` 0: no outlet speed)."""
    if rest_fraction > 0.0 and container.outlet_width <= 0.0:
        raise ValidationError("rest_fraction", "0 for a point outlet (outlet_width 0: no "
                              "outlet speed to take a share of)", f"got {rest_fraction:g}")


def at_rest(field: np.ndarray, discharge_rate: float, container,
            rest_fraction: float) -> np.ndarray:
    """``field`` (ny, nx, 2) [m/s] with the cells slower than ``rest_fraction``
    times the outlet speed set to 0 (module docstring)."""
    if rest_fraction <= 0.0 or discharge_rate <= 0.0:
        return field
    check_share(rest_fraction, container)
    threshold = rest_fraction * outlet_speed(discharge_rate, container)
    slow = np.hypot(field[..., 0], field[..., 1]) < threshold
    return np.where(slow[..., None], 0.0, field)


def fit(data, model, fractions=FRACTIONS, min_discharge: float = MIN_DISCHARGE) -> dict:
    """``fit_samples`` on the training samples of the design folder ``data``
    (``doe.load_samples``: discharge rates smoothed as the model was fitted)."""
    from surrogate.rom import doe

    return fit_samples(doe.load_samples(data), model, fractions, min_discharge)


def fit_samples(samples: dict, model, fractions=FRACTIONS,
                min_discharge: float = MIN_DISCHARGE) -> dict:
    """Youden's index of ``at_rest`` for each share in ``fractions`` on the
    training ``samples`` (``doe.load_samples``), the model's prediction at every
    sample discharging at least ``min_discharge`` [kg/s]. Returns
    ``{"fractions", "rest_stopped", "moving_stopped", "youden", "best", "cells"}``;
    with no discharging sample, a point outlet or no share with a positive index
    ``best`` is 0 (off)."""
    from surrogate.rom.transport import FILL

    container = model.container
    fractions = [float(f) for f in fractions]
    discharging = np.flatnonzero(samples["discharge_rate"] >= min_discharge)
    if container.outlet_width <= 0.0 or discharging.size == 0:
        return {"fractions": fractions, "rest_stopped": [], "moving_stopped": [],
                "youden": [], "best": 0.0, "cells": {"resting": 0, "moving": 0}}
    full = model.full_cell_mass
    resting, moving = [], []
    for k in discharging:
        cells = np.asarray(samples["mass"][k], dtype=np.float64)
        dem = np.asarray(samples["velocity"][k], dtype=np.float64)
        rate = float(samples["discharge_rate"][k])
        predicted = model.predict(cells, rate, float(samples["inflow_rate"][k]), check=False)
        share = np.hypot(predicted[..., 0], predicted[..., 1]) / outlet_speed(rate, container)
        speed = np.hypot(dem[..., 0], dem[..., 1])
        bulk = cells >= FILL * full
        resting.append(share[bulk & (speed < DEM_REST_SPEED)])
        moving.append(share[bulk & (speed > DEM_MOVING_SPEED)])
    resting, moving = np.concatenate(resting), np.concatenate(moving)
    rest_stopped = [float(np.mean(resting < f)) if resting.size else 0.0 for f in fractions]
    moving_stopped = [float(np.mean(moving < f)) if moving.size else 0.0 for f in fractions]
    youden = [r - m for r, m in zip(rest_stopped, moving_stopped)]
    return {"fractions": fractions, "rest_stopped": rest_stopped,
            "moving_stopped": moving_stopped, "youden": youden,
            # a share that stops no more resting than moving cells is no rule: off
            "best": fractions[int(np.argmax(youden))] if max(youden) > 0.0 else 0.0,
            "cells": {"resting": int(resting.size), "moving": int(moving.size)}}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m surrogate.rom.rest",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="exported training design folder")
    parser.add_argument("--model", default=None,
                        help="ROM model file (default: the default ROM, "
                             "data/paper_rom_loose.npz)")
    args = parser.parse_args(argv)
    from surrogate.rom.storage import load_model

    try:
        if not sorted(Path(args.data, "train").glob("*.npz")):
            raise ValidationError("--data", "a design folder with train/*.npz sample files",
                                  f"none under {args.data}")
        result = fit(args.data, load_model(args.model))
    except (ValidationError, OSError) as error:
        print(f"rest: error: {error}", file=sys.stderr)
        return 2
    print(f"bulk cells of discharging samples: {result['cells']['resting']} at rest in the DEM "
          f"(< {DEM_REST_SPEED:g} m/s), {result['cells']['moving']} moving "
          f"(> {DEM_MOVING_SPEED:g} m/s)")
    print("share  resting stopped  moving stopped  Youden")
    for row in zip(result["fractions"], result["rest_stopped"], result["moving_stopped"],
                   result["youden"]):
        print("{:5.2f}  {:15.3f}  {:14.3f}  {:6.3f}".format(*row))
    print(f"best share: {result['best']:g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
