"""Speed against accuracy of the stockpile fidelity ladder, and the pile pictures.

Issue 10 / paper sections "Integration test" and "Predicting the properties
of the mill feed": on the held-out scenario (300 s, rates and pile state not
in the ROM's training design) every storage model -- FIFO, perfect mixing,
the ROM at several POD mode counts, the DEM at two time steps -- is
scored by its tracking error (mean total-variation distance of the 30 s
outflow compositions per 15 t lot) against a fine-step DEM (dt = stable_dt /
2) and placed against its wall seconds per simulated second (log axis).
The DEM's chaos floor (two DEM runs 1e-6 m apart) is drawn as a line.

Writes into --out: ``speed_vs_accuracy.png``, ``speed_vs_accuracy.json``
(the points) and ``pile_fields.png`` (velocity, grade and hardness fields of
the DEM and the ROM at the middle of the held-out run, the paper's figure
"pileDistribution").

The chart uses the 200 kg/s held-out scenario (``heldout``); the data build
also runs the paper-throughput held-out scenarios that ``minetwin rom
evaluate`` scores (``surrogate.rom.doe.HELDOUT_SCENARIOS``).

Run (from the repository root; the first run builds the DEM data, about
10-20 minutes on 2 cores, later runs reuse it)::

    .venv/bin/python examples/speed_vs_accuracy.py --data examples/out/rom_data --out examples/out
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

DT_FACTORS = (0.5, 2.0)
"""DEM time steps run besides the default, as multiples of stable_dt; 0.5 is the
reference. (4 stable_dt was tried: the run slowed to a crawl, the mark of an
unstable step, so the ladder stops at 2.)"""

MODE_COUNTS = (2, 4, 8, 16)
"""POD mode counts (mass and velocity) of the ROM points."""


def progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default="examples/out/rom_data", help="DOE directory")
    parser.add_argument("--out", default="examples/out", help="output directory")
    parser.add_argument("--quick", action="store_true", help="small training design")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from surrogate.rom import evaluate as ev
    from surrogate.rom import metrics

    data, out = Path(args.data), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ev.build_data(data, quick=args.quick, seed=args.seed, progress=progress,
                  reference_dt_factors=DT_FACTORS)
    heldout = data / "heldout"
    fine = ev.load_run(heldout / "dem_dt0.5.npz")
    reference = ev.outflow_of(fine)
    t0 = float(fine["t0"])
    t1 = t0 + ev.scenario_duration(heldout)
    points = []

    def add(label, kind, outflow, wall):
        points.append({"label": label, "kind": kind,
                       "tracking_error": metrics.tracking_error(outflow, reference, t0, t1),
                       "wall_s_per_simulated_s": wall / (t1 - t0)})
        progress(f"{label}: {points[-1]}")

    for name in ("fifo", "mixing"):
        outflow, wall, _ = ev.run_storage(name, heldout)
        add(name.upper() if name == "fifo" else "perfect mixing", name, outflow, wall)
    captured = {}
    middle = int((t1 - t0) // 2)

    def capture(k, time, storage):
        if k == middle:
            captured.update(storage.fields(), time=time)

    default = ev.train(data)
    for modes in MODE_COUNTS:
        is_default = modes == default.n_mass_modes == default.n_velocity_modes
        model = default if is_default else ev.train(data, n_mass_modes=modes,
                                                    n_velocity_modes=modes)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ev.run_storage("rom", heldout, model)  # compile and warm up the kernels
            outflow, wall, _ = ev.run_storage("rom", heldout, model,
                                              on_step=capture if is_default else None)
        add(f"ROM {modes} modes" + (" (default)" if is_default else ""), "rom", outflow, wall)
    if not captured:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ev.run_storage("rom", heldout, default, on_step=capture)
    model = default
    for factor, name in [(1.0, "dem")] + [(f, f"dem_dt{f:g}") for f in DT_FACTORS if f > 1]:
        run = ev.load_run(heldout / f"{name}.npz")
        add(f"DEM dt = {factor:g} stable_dt", "dem", ev.outflow_of(run), float(run["wall_s"]))
    dem = ev.load_run(heldout / "dem.npz")
    floor = metrics.tracking_error(ev.outflow_of(ev.load_run(heldout / "dem_perturbed.npz")),
                                   ev.outflow_of(dem), t0, t1)
    fine_wall = float(fine["wall_s"]) / (t1 - t0)
    result = {"reference": f"DEM dt = 0.5 stable_dt ({fine_wall:.3g} wall s per simulated s)",
              "dem_noise_floor": floor, "points": points}
    (out / "speed_vs_accuracy.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))

    colours = {"fifo": "tab:red", "mixing": "tab:orange", "rom": "tab:blue", "dem": "tab:green"}
    fig, ax = plt.subplots(figsize=(7.5, 5))
    for k, p in enumerate(points):
        ax.scatter(p["wall_s_per_simulated_s"], p["tracking_error"], color=colours[p["kind"]],
                   s=40, zorder=3)
        right = k % 2 == 0  # alternate sides so neighbouring labels do not collide
        ax.annotate(p["label"], (p["wall_s_per_simulated_s"], p["tracking_error"]),
                    textcoords="offset points", xytext=(7 if right else -7, -3),
                    ha="left" if right else "right", fontsize=8)
    ax.axhline(floor, color="grey", ls="--", lw=1,
               label=f"DEM chaos floor (1e-6 m perturbation): {floor:.2f}")
    ax.axhline(0.10, color="black", ls=":", lw=1, label="target 0.10")
    ax.axvline(1.0, color="grey", ls="-", lw=0.5)
    ax.set_xscale("log")
    ax.set_ylim(0, 1)
    ax.set_xlabel("wall seconds per simulated second (one core; 1 = real time)")
    ax.set_ylabel("tracking error vs fine-step DEM (mean TV distance, 30 s windows)")
    ax.set_title("Stockpile fidelity ladder: what each second of compute buys")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "speed_vs_accuracy.png", dpi=130)
    plt.close(fig)

    grid = model.grid
    extent = (grid.x_min, grid.x_max, grid.y_min, grid.y_max)
    k = middle
    rows = {"DEM": {"mass": dem["field_mass"][k], "velocity": dem["field_velocity"][k],
                    "grade": dem["field_grade"][k], "hardness": dem["field_hardness"][k]},
            "ROM": captured}
    fig, axes = plt.subplots(2, 3, figsize=(13, 5.2), sharex=True, sharey=True)
    for r, (name, f) in enumerate(rows.items()):
        empty = f["mass"] <= 0
        speed = np.where(empty, np.nan, np.linalg.norm(f["velocity"], axis=-1))
        panels = (("speed [m/s]", speed, "viridis", None),
                  ("grade [-]", np.where(empty, np.nan, f["grade"]), "magma", (0.2, 0.8)),
                  ("hardness [-]", np.where(empty, np.nan, f["hardness"]), "coolwarm", (1, 2)))
        for c, (title, values, cmap, lim) in enumerate(panels):
            ax = axes[r, c]
            im = ax.imshow(values, origin="lower", extent=extent, cmap=cmap, aspect="equal",
                           vmin=None if lim is None else lim[0],
                           vmax=None if lim is None else lim[1])
            if c == 0:
                x, y = grid.centres()
                v = np.where(empty[..., None], np.nan, f["velocity"])
                ax.quiver(x, y, v[..., 0], v[..., 1], color="white", scale=8, width=0.002)
            ax.set_title(f"{name}: {title}", fontsize=9)
            fig.colorbar(im, ax=ax, shrink=0.7)
    axes[1, 0].set_xlabel("x [m]")
    axes[1, 0].set_ylabel("y [m]")
    fig.suptitle(f"Pile fields at t = {k} s of the held-out run "
                 "(the funnel zone drains in the near future)")
    fig.tight_layout()
    fig.savefig(out / "pile_fields.png", dpi=120)
    plt.close(fig)
    progress(f"wrote {out / 'speed_vs_accuracy.png'} and {out / 'pile_fields.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
