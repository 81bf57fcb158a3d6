"""Where the pile loses and gains mass: column fill of the ROM against the DEM replicas.

A diagnosis of the ROM on a held-out scene (``surrogate/rom/README.md``, "What
limits the accuracy now"): the held mass per grid column, over the scene, of the
ROM (``evaluate.run_storage``, the model and storage options given) and of each
DEM replica (its compact fields). In funnel flow the flanks of the pile rest and
the feeder draws through the core, which the inflow refills; a model that draws
the flanks down instead sends the inflow out late.

Where the flow passes (``row_flux``, ``line_flux``, ``edge_flux``): the downward
volume flux [m^2/s] through horizontal lines of the grid, summed over the core,
the funnel's edge (between the core and the flanks) and the flanks, and the
horizontal flux into the funnel through the vertical lines ``FLANKS[0]`` either
side of the feeder (cell mass times velocity over rho_A times the cell size,
the mean of the two cells beside the line): the DEM's own on replica 0's
states, the ROM's field before the transport at the DEM's mass, and the ROM's
own run at its transported field on the same seconds. The feeder's outflow
q_out / rho_A is what passes a line the bulk fills from wall to wall.

A column's fill [m] is its mass over rho_A dx (``Container.areal_density`` of the
model, the density a full ROM cell holds), i.e. the height the column would have
packed like the ROM's bulk. The DEM's bulk is looser (0.908 of rho_A on average,
``surrogate.rom.packing``), so compare changes, not levels: ``change`` is each
column's fill minus its fill at the start.

Run::

    python -m surrogate.rom.column_profile --data surrogate/rom/data/paper_heldout \\
        --scene heldout_q2000 --out DIR [--model FILE] [--velocity-model V] \\
        [--rest-fraction SHARE]

Writes ``column_profile_<scene>.json`` (columns' centres [m], sample times [s
after the start], fill per sample and column of the ROM and of every replica,
``row_flux``)
and ``column_profile_<scene>.png`` (the change at the end and the flanks' and
core's fill over time).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

from cosim import jsonio
from cosim.errors import ValidationError

CORE_HALF_WIDTH = 4.0
"""Columns within this distance [m] of the feeder's centre are the core (the
paper-scale feeder's half opening)."""

FLANKS = (12.0, 40.0)
"""Columns this far [m] from the feeder's centre are the flanks: beyond the
crater the 8 m feeder opens in the DEM (its pile rests there, ``method_score.
BULK_DISTANCE``) and short of the pile's toe."""


def column_fill(mass: np.ndarray, grid, areal_density: float) -> np.ndarray:
    """Fill [m] per column of mass fields ``(..., ny, nx)`` [kg]."""
    return np.asarray(mass, dtype=np.float64).sum(axis=-2) / (areal_density * grid.dx)


def profile(data, scene: str, model=None, options: dict | None = None,
            seed: int = 0) -> dict:
    """The ROM's and the DEM replicas' column fill on the held-out ``scene`` of the
    exported held-out design ``data``: ``{"x_m", "time_s", "rom", "dem": [...],
    "core", "flanks", "rom_flux"}`` (``core``/``flanks``: boolean column masks;
    ``rom_flux``, ``rom_edge_flux``: ``row_flux``'s on the ROM's own states, its
    mass moving at its transported field)."""
    from surrogate.dem import Dem
    from surrogate.rom import evaluate, heldout_layout
    from surrogate.rom.grid import mass_field
    from surrogate.rom.storage import load_model

    model = load_model(model)
    with heldout_layout.scenes_laid_out(data, [scene]) as (folder, _):
        heldout = folder / scene
        replicas = [evaluate.load_run(heldout / f"{name}.npz")
                    for name in evaluate.replica_names(evaluate.DEM_REPLICAS)
                    if (heldout / f"{name}.npz").is_file()]
        t0 = float(replicas[0]["t0"])
        times = np.asarray(replicas[0]["field_time"], dtype=np.float64) - t0
        sample = {int(round(t)): i for i, t in enumerate(times)}  # whole seconds after t0
        start = Dem.load_checkpoint(heldout / "initial.npz").snapshot()
        # the ROM starts from the DEM's own start state
        rom = {0: mass_field(model.grid, start["position"], start["mass"])}
        lines = flux_lines(model.grid, ROW_FLUX_HEIGHTS)
        x = model.grid.centres()[0]
        columns = regions(x, model.container.outlet_x)
        masks = list(columns.values())
        rom_flux, rom_edge = [], []  # on the states row_flux takes of the DEM's

        def capture(k, time, storage):  # called after the step that ends at ``time``
            at = int(round(time - t0))
            if at in sample:
                fields = storage.fields()
                rom[sample[at]] = fields["mass"]
                if sample[at] % ROW_FLUX_EVERY == 0:
                    density = storage.container.areal_density
                    rom_flux.append(line_flux(fields["mass"], fields["velocity"], model.grid,
                                              density, lines, masks))
                    rom_edge.append(edge_flux(fields["mass"], fields["velocity"], model.grid,
                                              density, model.container.outlet_x))

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            evaluate.run_storage("rom", heldout, model, seed=seed, options=options,
                                 on_step=capture)
    grid, density = model.grid, model.container.areal_density
    steps = sorted(rom)
    dem = [column_fill(r["field_mass"][steps], grid, density) for r in replicas]
    return {"scene": scene, "x_m": x, "time_s": times[steps],
            "rom": column_fill(np.array([rom[k] for k in steps]), grid, density),
            "dem": dem, "core": columns["core"], "flanks": columns["flanks"],
            "rom_flux": np.mean(rom_flux, axis=0), "rom_edge_flux": np.mean(rom_edge, axis=0)}


ROW_FLUX_HEIGHTS = (4.0, 10.0, 16.0, 22.0, 26.0)
"""Heights [m] above the grid's bottom of the lines ``row_flux`` reports (grid lines
of the paper-scale 2 m grid)."""

ROW_FLUX_EVERY = 10
"""``row_flux`` takes every this many of replica 0's samples (one per second)."""


def regions(x: np.ndarray, outlet_x: float) -> dict:
    """Boolean column masks of the core, the funnel's edge and the flanks."""
    distance = np.abs(x - outlet_x)
    return {"core": distance <= CORE_HALF_WIDTH,
            "funnel edge": (distance > CORE_HALF_WIDTH) & (distance < FLANKS[0]),
            "flanks": (distance >= FLANKS[0]) & (distance <= FLANKS[1])}


def line_flux(mass: np.ndarray, velocity: np.ndarray, grid, areal_density: float,
              lines, masks) -> np.ndarray:
    """Downward volume flux [m^2/s] (len(lines), len(masks)) through the grid lines
    ``lines`` (row indices: the line under that row) of a mass field (ny, nx) [kg]
    moving at ``velocity`` (ny, nx, 2) [m/s]: cell mass times downward speed over
    rho_A dy, the mean of the two cells beside the line, summed over each mask's
    columns."""
    flux = -np.asarray(mass, np.float64) * np.asarray(velocity, np.float64)[..., 1] / (
        areal_density * grid.dy)
    return np.array([[0.5 * (flux[j - 1] + flux[j])[mask].sum() for mask in masks]
                     for j in lines])


def edge_flux(mass: np.ndarray, velocity: np.ndarray, grid, areal_density: float,
              outlet_x: float) -> np.ndarray:
    """Horizontal volume flux [m^2/s] per row (ny,) into the funnel through the
    vertical grid lines ``FLANKS[0]`` either side of the feeder (towards the
    feeder positive): cell mass times horizontal speed over rho_A dx, the mean of
    the two cells beside the line, both sides summed."""
    flux = np.asarray(mass, np.float64) * np.asarray(velocity, np.float64)[..., 0] / (
        areal_density * grid.dx)
    total = np.zeros(grid.ny)
    for side in (-1.0, 1.0):
        i = int(round((outlet_x + side * FLANKS[0] - grid.x_min) / grid.dx))
        total -= side * 0.5 * (flux[:, i - 1] + flux[:, i])
    return total


def row_flux(data, scene: str, model=None, options: dict | None = None,
             heights=ROW_FLUX_HEIGHTS, every: int = ROW_FLUX_EVERY) -> dict:
    """Mean downward volume flux [m^2/s] through the grid lines at ``heights``
    per region (``regions``) on every ``every``-th state of the scene's DEM
    replica 0: the DEM's own and the ROM's field before the transport at the
    DEM's mass (``{"heights_m", "regions", "outflow_m2_s", "dem", "predicted"}``,
    the last two (len(heights), 3)) and the flux into the funnel through its edge
    per row (``edge_flux``: ``"edge_dem"``, ``"edge_predicted"``). The ROM's own
    run: ``profile``'s ``rom_flux`` and ``rom_edge_flux``."""
    from surrogate.rom.storage import RomStorage

    path = Path(data) / "train" / f"{scene}_r0.npz"
    if not path.is_file():
        raise ValidationError("--scene", "a scene of the held-out design with its replica 0",
                              f"no {path}")
    storage = RomStorage(model, **(options or {}))
    grid, density = storage.model.grid, storage.container.areal_density
    lines = flux_lines(grid, heights)
    outlet_x = storage.container.outlet_x
    columns = regions(grid.centres()[0], outlet_x)
    masks = list(columns.values())
    dem, predicted, dem_edge, predicted_edge = [], [], [], []
    with np.load(path) as run:
        for k in range(0, run["time"].size, every):
            mass = run["mass"][k].astype(np.float64)
            field = storage.predicted_field(mass, float(run["discharge_rate"][k]),
                                            float(run["inflow_rate"][k]))
            dem.append(line_flux(mass, run["velocity"][k], grid, density, lines, masks))
            predicted.append(line_flux(mass, field, grid, density, lines, masks))
            dem_edge.append(edge_flux(mass, run["velocity"][k], grid, density, outlet_x))
            predicted_edge.append(edge_flux(mass, field, grid, density, outlet_x))
        outflow = float(np.mean(run["discharge_rate"][::every])) / density
    return {"heights_m": [grid.y_min + j * grid.dy for j in lines],
            "regions": list(columns), "outflow_m2_s": outflow,
            "dem": np.mean(dem, axis=0).tolist(), "predicted": np.mean(predicted, axis=0).tolist(),
            "edge_dem": np.mean(dem_edge, axis=0).tolist(),
            "edge_predicted": np.mean(predicted_edge, axis=0).tolist()}


def flux_lines(grid, heights) -> list[int]:
    """Row indices of the grid lines at ``heights`` [m above the grid's bottom]."""
    lines = [int(round((h - grid.y_min) / grid.dy)) for h in heights]
    if any(not 0 < j < grid.ny for j in lines):
        raise ValidationError("heights", f"inside the grid ({grid.y_min:g}-{grid.y_max:g} m)",
                              f"got {list(heights)}")
    return lines


def summary(result: dict) -> dict:
    """Mean change [m] of the core's and the flanks' fill from start to end, ROM
    and each replica."""
    def change(fill, mask):
        return float((fill[-1] - fill[0])[mask].mean())

    return {"rom": {"core_change_m": change(result["rom"], result["core"]),
                    "flank_change_m": change(result["rom"], result["flanks"])},
            "dem": [{"core_change_m": change(d, result["core"]),
                     "flank_change_m": change(d, result["flanks"])} for d in result["dem"]]}


def plot(result: dict, path: Path) -> None:
    from cosim import plotstyle

    plt = plotstyle.pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(14, 5))
    x, times = result["x_m"], result["time_s"]
    rom, dem = result["rom"], result["dem"]
    left.plot(x, rom[-1] - rom[0], color="tab:blue", lw=2, label="ROM")
    for k, fill in enumerate(dem):
        left.plot(x, fill[-1] - fill[0], color="tab:green", lw=1, alpha=0.5 + 0.2 * k,
                  label=f"DEM replica {k}")
    left.axhline(0.0, color="grey", lw=0.5, label="no change")
    left.set_xlim(-45.0, 45.0)
    left.set_xlabel("x [m]")
    left.set_ylabel("column fill change [m]")
    left.set_title(f"change over the {times[-1]:.0f} s")
    plotstyle.legend(left, fontsize=8)
    for mask, name, style in ((result["core"], "core", "-"),
                              (result["flanks"], "flanks", "--")):
        right.plot(times, rom[:, mask].mean(axis=1), color="tab:blue", ls=style, lw=2,
                   label=f"ROM, {name}")
        for k, fill in enumerate(dem):
            right.plot(times, fill[:, mask].mean(axis=1), color="tab:green", ls=style, lw=1,
                       alpha=0.5 + 0.2 * k, label=f"DEM replica {k}, {name}")
    right.set_xlabel("time since the scene's start [s]")
    right.set_ylabel("mean column fill [m]")
    right.set_title(f"core (|x| <= {CORE_HALF_WIDTH:g} m) and flanks "
                    f"({FLANKS[0]:g} m <= |x| <= {FLANKS[1]:g} m)")
    plotstyle.legend(right, fontsize=7)
    plotstyle.title(fig, f"{result['scene']}: where the pile loses and gains mass",
                    "column fill = column mass / (rho_A dx), rho_A of the ROM's container")
    fig.tight_layout()
    plotstyle.save(fig, path, dpi=110)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m surrogate.rom.column_profile",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="exported held-out design folder")
    parser.add_argument("--scene", required=True, help="held-out scene, e.g. heldout_q2000")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--model", default=None,
                        help="ROM model file (default: the default ROM, "
                             "data/paper_rom_loose.npz)")
    parser.add_argument("--velocity-model", choices=("regressed", "kinematic", "hybrid"),
                        default="regressed", help="RomStorage's velocity_model (regressed)")
    parser.add_argument("--rest-fraction", type=float, default=None,
                        help="RomStorage's rest_fraction (default: the model file's; 0: off; "
                             "surrogate.rom.rest)")
    parser.add_argument("--seed", type=int, default=0, help="ROM seed (0)")
    args = parser.parse_args(argv)
    options = {"velocity_model": args.velocity_model,
               **({} if args.rest_fraction is None else {"rest_fraction": args.rest_fraction})}
    try:
        result = profile(args.data, args.scene, args.model, options, args.seed)
        passing = row_flux(args.data, args.scene, args.model, options)
    except (ValidationError, OSError) as error:
        print(f"column_profile: error: {error}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"column_profile_{args.scene}"
    found = summary(result)
    jsonio.write(stem.with_suffix(".json"),
                 {**{k: (v.tolist() if isinstance(v, np.ndarray) else v)
                     for k, v in result.items() if k != "dem"},
                  "dem": [d.tolist() for d in result["dem"]], "summary": found,
                  "row_flux": passing}, indent=1)
    plot(result, stem.with_suffix(".png"))
    dem = found["dem"]
    print(f"{args.scene}: core fill change ROM {found['rom']['core_change_m']:+.2f} m, DEM "
          + " / ".join(f"{d['core_change_m']:+.2f}" for d in dem)
          + f"; flanks ROM {found['rom']['flank_change_m']:+.2f} m, DEM "
          + " / ".join(f"{d['flank_change_m']:+.2f}" for d in dem))
    print(f"downward volume flux [m^2/s] on replica 0's states (outflow q_out / rho_A "
          f"{passing['outflow_m2_s']:.2f}), " + " | ".join(passing["regions"]) + ":")
    rows = {"DEM": passing["dem"], "predicted at the DEM's mass": passing["predicted"],
            "ROM's own run": result["rom_flux"]}
    for a, height in enumerate(passing["heights_m"]):
        print(f"  {height:4.0f} m  " + "   ".join(
            f"{key} " + " | ".join(f"{f:5.2f}" for f in values[a])
            for key, values in rows.items()))
    print(f"into the funnel through |x - outlet| = {FLANKS[0]:g} m, summed over the rows "
          f"[m^2/s]: DEM {sum(passing['edge_dem']):.2f}, predicted at the DEM's mass "
          f"{sum(passing['edge_predicted']):.2f}, ROM's own run {result['rom_edge_flux'].sum():.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
