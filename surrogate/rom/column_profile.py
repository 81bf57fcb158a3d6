"""Where the pile loses and gains mass: column fill of the ROM against the DEM replicas.

A diagnosis of the ROM on a held-out scene (``surrogate/rom/README.md``, "What
limits the accuracy now"): the held mass per grid column, over the scene, of the
ROM (``evaluate.run_storage``, the model and storage options given) and of each
DEM replica (its compact fields). In funnel flow the flanks of the pile rest and
the feeder draws through the core, which the inflow refills; a model that draws
the flanks down instead sends the inflow out late.

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
after the start], fill per sample and column of the ROM and of every replica)
and ``column_profile_<scene>.png`` (the change at the end and the flanks' and
core's fill over time).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
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
    "core", "flanks"}`` (``core``/``flanks``: boolean column masks)."""
    from surrogate.dem import Dem
    from surrogate.rom import evaluate, heldout_layout
    from surrogate.rom.grid import mass_field
    from surrogate.rom.model import RomModel
    from surrogate.rom.storage import DEFAULT_MODEL

    model = RomModel.load(model or DEFAULT_MODEL)
    with tempfile.TemporaryDirectory() as folder:
        layout = heldout_layout.write_layout(data, folder)
        names = [s["name"] for s in layout["scenes"]]
        if scene not in names:
            raise ValidationError("--scene", f"one of {names}", f"got {scene!r}")
        heldout = Path(folder) / scene
        replicas = [evaluate.load_run(heldout / f"{name}.npz")
                    for name in evaluate.replica_names(evaluate.DEM_REPLICAS)
                    if (heldout / f"{name}.npz").is_file()]
        t0 = float(replicas[0]["t0"])
        times = np.asarray(replicas[0]["field_time"], dtype=np.float64) - t0
        sample = {int(round(t)): i for i, t in enumerate(times)}  # whole seconds after t0
        start = Dem.load_checkpoint(heldout / "initial.npz").snapshot()
        # the ROM starts from the DEM's own start state
        rom = {0: mass_field(model.grid, start["position"], start["mass"])}

        def capture(k, time, storage):  # called after the step that ends at ``time``
            at = int(round(time - t0))
            if at in sample:
                rom[sample[at]] = storage.fields()["mass"]

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            evaluate.run_storage("rom", heldout, model, seed=seed, options=options,
                                 on_step=capture)
    grid, density = model.grid, model.container.areal_density
    steps = sorted(rom)
    x = grid.x_min + grid.dx * (np.arange(grid.nx) + 0.5)
    dem = [column_fill(r["field_mass"][steps], grid, density) for r in replicas]
    distance = np.abs(x - model.container.outlet_x)
    return {"scene": scene, "x_m": x, "time_s": times[steps],
            "rom": column_fill(np.array([rom[k] for k in steps]), grid, density),
            "dem": dem, "core": distance <= CORE_HALF_WIDTH,
            "flanks": (distance >= FLANKS[0]) & (distance <= FLANKS[1])}


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
    parser.add_argument("--model", default=None, help="ROM model file (default: the shipped one)")
    parser.add_argument("--velocity-model", choices=("regressed", "kinematic", "hybrid"),
                        default="regressed", help="RomStorage's velocity_model (regressed)")
    parser.add_argument("--rest-fraction", type=float, default=None,
                        help="RomStorage's rest_fraction (default: the model file's; 0: off; "
                             "surrogate.rom.rest)")
    parser.add_argument("--seed", type=int, default=0, help="ROM seed (0)")
    args = parser.parse_args(argv)
    try:
        result = profile(args.data, args.scene, args.model,
                         {"velocity_model": args.velocity_model,
                          **({} if args.rest_fraction is None
                             else {"rest_fraction": args.rest_fraction})}, args.seed)
    except (ValidationError, OSError) as error:
        print(f"column_profile: error: {error}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"column_profile_{args.scene}"
    found = summary(result)
    jsonio.write(stem.with_suffix(".json"),
                 {**{k: (v.tolist() if isinstance(v, np.ndarray) else v)
                     for k, v in result.items() if k != "dem"},
                  "dem": [d.tolist() for d in result["dem"]], "summary": found}, indent=1)
    plot(result, stem.with_suffix(".png"))
    dem = found["dem"]
    print(f"{args.scene}: core fill change ROM {found['rom']['core_change_m']:+.2f} m, DEM "
          + " / ".join(f"{d['core_change_m']:+.2f}" for d in dem)
          + f"; flanks ROM {found['rom']['flank_change_m']:+.2f} m, DEM "
          + " / ".join(f"{d['flank_change_m']:+.2f}" for d in dem))
    return 0


if __name__ == "__main__":
    sys.exit(main())
