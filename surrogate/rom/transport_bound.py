"""How far the ROM's transport can track when its field is the DEM's own.

A diagnosis of the ROM on the scenes of an exported held-out design
(``surrogate/rom/README.md``, "What the transport can reach"). The ROM of the
paper (sections "Digital twin as a distributed particle simulation" and
"Integration test"; Wallin and Servin 2021) predicts a velocity field on its
grid and moves the bulk's particles by it (``surrogate.rom.transport``,
packing, feeder, surface layer). Here the prediction is replaced by the field
of a DEM replica of the same scene (its ``field_velocity``, mass-weighted mean
velocity per grid cell, sampled every second): at time t the mean of the
replica's fields sampled within ``half_window`` [s] of t (the nearest sample
when none is). Scored against the *other* replicas only (the field's own
replica would score it against itself), the tracking error is what a fit that
predicted the DEM's field exactly would reach through this transport.

Two more fields (``--field``) tell which part of the fit limits it:

- ``modes:K``: the replica's field projected on the first K modes of the
  uncentred POD of the training design's velocity samples (the basis the
  paper's regression, Wallin and Servin 2021, predicts in; ``RomModel``'s
  ``pod_basis``, so K = 4 is the fixed-grid model's own basis, data/paper_rom.npz): what a
  fit that got every coefficient of a K-mode basis right would reach;
- ``model``: the model's prediction at the replica's own mass field (window
  mean as above) and the storage's rates, with its resting bulk: the fit
  without the drift of the ROM's own pile (open loop).

Two things make the DEM's field fit the ROM's pile, which is not the DEM's:

- The DEM's field is 0 wherever the DEM had no bulk, so ROM particles above
  the DEM's surface would never move. In every column the field above the
  highest cell holding at least ``packing.ABOVE_FILL`` of a full cell
  (rho_A dx dy) takes that cell's value (``extended``).
- The field moves the DEM's bulk, which is looser than the ROM's container
  packs (``surrogate.rom.packing``: 564.2 kg/m^2 on the paper design against
  621.1). At the container's density the ROM's surface heights, where the
  inflow lands, lie 3-4 m under the DEM pile's top near the feeder's axis, so
  the storage runs at the DEM's mean settled density
  (``RomStorage(packing_density=...)``, default: measured by
  ``packing.settled_density`` on the shipped model's training design,
  ``TRAINING_DESIGN``).

For each scene it reports, from ``evaluate.ensemble_score`` and
``evaluate.noise_floor`` (tracking error, ``surrogate.rom.metrics``, issue 10):

- ``dem_noise_floor``: the replicas against each other, every pair once;
- ``rom``: the model (default the default ROM, ``storage.DEFAULT_MODEL``; its fitted field, its own
  density), every ROM seed against every replica;
- ``bounds``: per (field, half window, packing, landing spread) the ROM with each
  replica's field, every (replica, ROM seed) against each other replica;

each as the spread (mean, min, max, std, n) of the tracking error, of the same
error with the inflow's ids as one (``tracking_split.lumped``: the inflow's share
and the start pile's lots), and the mean distance per 30 s window.

Run::

    python -m surrogate.rom.transport_bound --data surrogate/rom/data/paper_heldout \\
        --out DIR [--scene S] [--half-window 0 --half-window 15 ...] \\
        [--packing none --packing avalanche] [--packing-density KG_M2] [--rom-seeds N] \\
        [--landing-spread 0 --landing-spread 3 ...] [--field dem --field modes:16 \\
        --field model ...] [--model FILE]

Defaults: half windows 0, 15 and 180 s (the sample nearest t, a 30 s mean, the
whole scene), packings "none" and "avalanche" (the shipped one), landing spread
0 m (``RomStorage(landing_spread=...)``), the field "dem", 2 ROM seeds.
Writes ``transport_bound.json`` and ``transport_bound.png`` and prints one
table per scene.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import warnings
from functools import partial
from pathlib import Path

import numpy as np

from cosim import jsonio
from cosim.errors import ValidationError, check_finite_range
from surrogate.rom import doe, evaluate, metrics
from surrogate.rom.model import pod_basis
from surrogate.rom.packing import ABOVE_FILL, settled_density
from surrogate.rom.storage import PACKINGS, RomStorage
from surrogate.rom.tracking_split import lumped

HALF_WINDOWS = (0.0, 15.0, 180.0)
"""Default half windows [s] of the replayed field's time mean."""

ROM_SEEDS = 2
"""Default number of ROM seeds (0 .. N-1) per run."""

PACKINGS_SCORED = ("none", "avalanche")
"""Default packings of the ROM with the DEM's field (``RomStorage(packing=...)``)."""

LANDING_SPREADS = (0.0,)
"""Default landing spreads [m] of the ROM with the DEM's field
(``RomStorage(landing_spread=...)``): none."""

FIELDS = ("dem",)
"""Default fields replayed: the replica's own."""

TRAINING_DESIGN = Path(__file__).resolve().parent / "data" / "paper_design"
"""The shipped models' training design, where the default packing density is
measured and the ``modes:K`` fields' basis is taken."""


def check_field(text: str) -> str:
    """``text`` if it names a field (module docstring): "dem", "model" or
    "modes:K" with K a whole number >= 1; else ``ValidationError`` on ``--field``."""
    kind, _, count = str(text).partition(":")
    if (kind in ("dem", "model") and not count) or (
            kind == "modes" and count.isdigit() and int(count) >= 1):
        return str(text)
    raise ValidationError("--field", "dem, model or modes:K (K a whole number >= 1)",
                          f"got {text!r}")


def mode_count(field: str) -> int | None:
    """K of a checked ``modes:K`` field (``check_field``); None for the others."""
    kind, _, count = field.partition(":")
    return int(count) if kind == "modes" else None


def velocity_basis(design=TRAINING_DESIGN) -> np.ndarray:
    """The orthonormal modes (modes, 2 cells) of the uncentred POD of ``design``'s
    velocity samples, most energetic first (``RomModel``'s velocity basis)."""
    return pod_basis(doe.load_samples(design)["velocity"], centred=False)[2]


def projected(velocity: np.ndarray, modes: np.ndarray) -> np.ndarray:
    """``velocity`` (S, ny, nx, 2) [m/s], each sample projected on the orthonormal
    ``modes`` (K, 2 cells)."""
    flat = np.asarray(velocity, dtype=np.float64).reshape(len(velocity), -1)
    return ((flat @ modes.T) @ modes).reshape(np.shape(velocity))


def window_mean(times: np.ndarray, fields: np.ndarray, t: float, half_window: float) -> np.ndarray:
    """Mean of ``fields`` (S, ...) over the samples at ``times`` (S,) [s] within
    ``half_window`` [s] of ``t``; the sample nearest ``t`` when none is."""
    near = np.abs(times - t) <= half_window
    if not near.any():
        near = np.arange(times.size) == np.argmin(np.abs(times - t))
    return fields[near].mean(axis=0)


def extended(velocity: np.ndarray, mass: np.ndarray, full_cell_mass: float) -> np.ndarray:
    """Fields ``velocity`` (S, ny, nx, 2) [m/s] with every cell above a column's
    highest cell holding at least ``packing.ABOVE_FILL`` x ``full_cell_mass`` [kg]
    of ``mass`` (S, ny, nx) [kg] given that cell's value (a column without one
    is left as it is)."""
    filled = np.asarray(mass) >= ABOVE_FILL * full_cell_mass
    rows = np.arange(filled.shape[1])[None, :, None]
    top = np.where(filled, rows, -1).max(axis=1, keepdims=True)  # (S, 1, nx)
    source = np.where((top >= 0) & (rows > top), top, rows)
    return np.take_along_axis(np.asarray(velocity), source[..., None], axis=1)


def _checked_fields(grid, field_time, field_mass, half_window: float, field_velocity=None):
    """The run's samples as float64 arrays, checked against the model's ``grid``:
    ``(time, mass, velocity or None, half window)``."""
    mass = np.asarray(field_mass, dtype=np.float64)
    if mass.ndim != 3 or mass.shape[1:] != (grid.ny, grid.nx):
        raise ValidationError("field_mass", f"(S, {grid.ny}, {grid.nx}) on the model's grid",
                              f"got {mass.shape}")
    velocity = None
    if field_velocity is not None:
        velocity = np.asarray(field_velocity, dtype=np.float64)
        if velocity.shape[1:] != (grid.ny, grid.nx, 2):
            raise ValidationError("field_velocity", f"(S, {grid.ny}, {grid.nx}, 2) on the "
                                  "model's grid", f"got {velocity.shape}")
        if mass.shape != velocity.shape[:-1]:
            raise ValidationError("field_mass", f"{velocity.shape[:-1]}, as field_velocity",
                                  f"got {mass.shape}")
    return (np.asarray(field_time, dtype=np.float64), mass, velocity,
            float(check_finite_range("half_window", half_window, 0.0, unit="s")))


class ReplayedField(RomStorage):
    """The ROM with a DEM run's own velocity field in place of its prediction.

    ``field_time`` (S,) [s], ``field_velocity`` (S, ny, nx, 2) [m/s] and
    ``field_mass`` (S, ny, nx) [kg] are the run's samples on the model's grid;
    the field at time t is the ``window_mean`` with ``half_window`` [s] (>= 0) of
    the velocities, projected on ``modes`` (K, 2 cells; orthonormal rows) when
    given, ``extended`` above the DEM's pile (module docstring). The resting bulk
    is the DEM's own (``rest_fraction`` plays no part); every other option is
    ``RomStorage``'s.
    """

    def __init__(self, model=None, *, field_time, field_velocity, field_mass,
                 half_window: float, modes=None, **options):
        super().__init__(model, **options)
        grid = self.model.grid
        self.field_time, mass, velocity, self.half_window = _checked_fields(
            grid, field_time, field_mass, half_window, field_velocity)
        if modes is not None:
            velocity = projected(velocity, modes)
        self.field_velocity = extended(velocity, mass, self.model.container.full_cell_mass(grid))

    def _predicted(self, t: float, discharge_rate: float, mass: np.ndarray) -> np.ndarray:
        return window_mean(self.field_time, self.field_velocity, t, self.half_window)


class FittedAtDemState(RomStorage):
    """The ROM with its model's field predicted at a DEM run's own mass field
    (open loop): at time t, ``predicted_field`` (the fit and the resting bulk) of
    the ``window_mean`` with ``half_window`` [s] of ``field_mass`` (S, ny, nx) [kg]
    sampled at ``field_time`` (S,) [s], at the storage's discharge and inflow
    rates; every other option is ``RomStorage``'s."""

    def __init__(self, model=None, *, field_time, field_mass, half_window: float, **options):
        super().__init__(model, **options)
        self.field_time, self.field_mass, _, self.half_window = _checked_fields(
            self.model.grid, field_time, field_mass, half_window)

    def _predicted(self, t: float, discharge_rate: float, mass: np.ndarray) -> np.ndarray:
        dem_mass = window_mean(self.field_time, self.field_mass, t, self.half_window)
        return self.predicted_field(dem_mass, discharge_rate, self.inflow_rate(t))


def _scored(runs: list[tuple[dict, list[dict]]], inflow_ids, t0: float, t1: float) -> dict:
    """Spreads of the tracking error and the lumped one, and the mean distance per
    window, over every (run, reference) pair of ``runs`` ((outflow, references))."""
    full, merged, windows = [], [], []
    for outflow, references in runs:
        full += evaluate.ensemble_score(outflow, references, t0, t1)["tracking_errors"]
        merged += evaluate.ensemble_score(lumped(outflow, inflow_ids),
                                          [lumped(r, inflow_ids) for r in references],
                                          t0, t1)["tracking_errors"]
        windows += [metrics.window_distances(outflow, r, t0, t1) for r in references]
    return {"tracking_error": evaluate.spread(full), "lumped": evaluate.spread(merged),
            "window_distance": [float(v) for v in np.mean(windows, axis=0)]}


def _run(heldout: Path, model, seed: int, options: dict, build=None) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # out-of-range warnings: the field is not the model's
        outflow, _, _ = evaluate.run_storage("rom", heldout, model, seed=seed, options=options,
                                             build=build)
    return outflow


def _builder(field: str, replica: dict, half_window: float, basis):
    """The storage factory (``evaluate.run_storage``'s ``build``) of ``field``
    (``check_field``) for one replica."""
    if field == "model":
        return partial(FittedAtDemState, field_time=replica["field_time"],
                       field_mass=replica["field_mass"], half_window=half_window)
    modes = None if field == "dem" else basis[:mode_count(field)]
    return partial(ReplayedField, field_time=replica["field_time"],
                   field_velocity=replica["field_velocity"], field_mass=replica["field_mass"],
                   half_window=half_window, modes=modes)


def bound_scene(model, heldout: Path, packing_density: float, half_windows=HALF_WINDOWS,
                packings=PACKINGS_SCORED, rom_seeds: int = ROM_SEEDS, progress=None,
                landing_spreads=LANDING_SPREADS, fields=FIELDS, basis=None) -> dict:
    """The floor, the model's ROM and the bounds (module docstring) on the held-out
    scene folder ``heldout`` (``evaluate``'s layout), the ROM with each replica's
    field packed at ``packing_density`` [kg/m^2], one bound per (field, half
    window, packing, landing spread [m], ``RomStorage(landing_spread=...)``);
    ``basis``: ``velocity_basis``, needed by ``modes:K`` fields."""
    replicas = evaluate.stable_replicas(heldout)
    references = [evaluate.outflow_of(run) for run in replicas]
    if len(references) < 2:
        raise ValidationError("replicas", "at least 2 stable DEM replicas of the scene",
                              f"{len(references)} under {heldout}")
    t0 = float(replicas[0]["t0"])
    t1 = t0 + evaluate.scenario_duration(heldout)
    with np.load(heldout / "emissions.npz") as stored:
        inflow_ids = np.unique(stored["tracking_id"])
    pairs = [(references[i], [references[j]]) for i in range(len(references))
             for j in range(i + 1, len(references))]
    result = {"replicas": len(references), "rom_seeds": rom_seeds, "window_s": metrics.WINDOW_S,
              "packing_density_kg_m2": packing_density,
              "dem_noise_floor": _scored(pairs, inflow_ids, t0, t1),
              "rom": _scored([(_run(heldout, model, seed, {}), references)
                              for seed in range(rom_seeds)], inflow_ids, t0, t1),
              "bounds": []}
    for field, half_window, packing, spread in itertools.product(
            fields, half_windows, packings, landing_spreads):
        if progress is not None:
            progress(f"{heldout.name}: field {field}, half window {half_window:g} s, "
                     f"packing {packing}, landing spread {spread:g} m")
        runs = []
        for k, replica in enumerate(replicas):
            others = references[:k] + references[k + 1:]
            options = {"packing": packing, "packing_density": packing_density,
                       "landing_spread": spread}
            build = _builder(field, replica, half_window, basis)
            runs += [(_run(heldout, model, seed, options, build), others)
                     for seed in range(rom_seeds)]
        result["bounds"].append({"field": field, "half_window_s": float(half_window),
                                 "packing": packing, "landing_spread_m": float(spread),
                                 **_scored(runs, inflow_ids, t0, t1)})
    return result


def bound(data, scenes=None, half_windows=HALF_WINDOWS, packings=PACKINGS_SCORED,
          rom_seeds: int = ROM_SEEDS, model=None, packing_density: float | None = None,
          progress=None, landing_spreads=LANDING_SPREADS, fields=FIELDS) -> dict:
    """``bound_scene`` on ``scenes`` (default all) of the exported held-out design
    ``data``: ``{scene: result}``. ``packing_density`` [kg/m^2] defaults to the
    DEM's mean settled density on ``TRAINING_DESIGN``, the ``modes:K`` fields'
    basis is ``velocity_basis`` of ``TRAINING_DESIGN``."""
    from surrogate.rom import heldout_layout
    from surrogate.rom.storage import load_model

    rom_seeds = evaluate.check_rom_seeds(rom_seeds)
    for half_window in half_windows:
        check_finite_range("--half-window", half_window, 0.0, unit="s")
    for spread in landing_spreads:
        check_finite_range("--landing-spread", spread, 0.0, unit="m")
    for packing in packings:
        if packing not in PACKINGS:
            raise ValidationError("--packing", f"one of {PACKINGS}", f"got {packing!r}")
    fields = [check_field(field) for field in fields]
    basis = None
    most = max((mode_count(field) or 0 for field in fields), default=0)
    if most:
        basis = velocity_basis()
        if most > basis.shape[0]:
            raise ValidationError("--field", f"modes:K with K at most {basis.shape[0]} "
                                  "(the training design's samples)", f"got modes:{most}")
    if packing_density is None:
        packing_density = settled_density(TRAINING_DESIGN)["density"]
    packing_density = float(check_finite_range("--packing-density", packing_density, 0.0,
                                               low_open=True, unit="kg/m^2"))
    model = load_model(model)
    if basis is not None and basis.shape[1] != 2 * model.grid.n_cells:
        raise ValidationError("--field", "modes:K with a model on the grid of "
                              f"{TRAINING_DESIGN.name}, whose velocities give the modes",
                              f"the model's grid is {model.grid.shape}")
    with heldout_layout.scenes_laid_out(data, scenes) as (folder, names):
        return {name: bound_scene(model, folder / name, packing_density, half_windows,
                                  packings, rom_seeds, progress, landing_spreads, fields,
                                  basis)
                for name in names}


def _row(name: str, entry: dict) -> str:
    full, merged = entry["tracking_error"], entry["lumped"]
    return (f"  {name:62} {full['mean']:.3f} ({full['min']:.3f}-{full['max']:.3f})   "
            f"{merged['mean']:.3f}   " + " ".join(f"{v:.2f}" for v in entry["window_distance"]))


def _spread_label(entry: dict) -> str:
    spread = entry["landing_spread_m"]
    return f", landing sd {spread:g} m" if spread else ""


def _field_label(entry: dict) -> str:
    field = entry["field"]
    if field == "model":
        return f"fit at DEM state ±{entry['half_window_s']:g} s"
    name = "DEM field" if field == "dem" else f"DEM field, {mode_count(field)} modes,"
    return f"{name} ±{entry['half_window_s']:g} s"


def report(scene: str, result: dict) -> str:
    """The printed table of one scene."""
    lines = [f"{scene} ({result['replicas']} DEM replicas, ROM seeds 0-{result['rom_seeds'] - 1}, "
             f"replayed fields at {result['packing_density_kg_m2']:.1f} kg/m^2): tracking "
             f"error mean (min-max), inflow ids as one, per {result['window_s']:g} s window",
             _row("DEM noise floor", result["dem_noise_floor"]),
             _row("ROM, its fitted field", result["rom"])]
    lines += [_row(f"ROM, {_field_label(b)}, {b['packing']}" + _spread_label(b), b)
              for b in result["bounds"]]
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    from cosim import plotstyle

    plt = plotstyle.pyplot()
    fig, axes = plt.subplots(1, len(results), figsize=(5.5 * len(results), 6.5), squeeze=False)
    for ax, (scene, result) in zip(axes[0], results.items()):
        entries = [("DEM noise floor", result["dem_noise_floor"], "tab:grey"),
                   ("ROM, its fitted field", result["rom"], "tab:blue")]
        colours = plt.get_cmap("Greens")(np.linspace(0.4, 0.9, max(len(result["bounds"]), 1)))
        entries += [(f"{_field_label(b)}, packing {b['packing']}" + _spread_label(b), b,
                     colours[k])
                    for k, b in enumerate(result["bounds"])]
        for k, (label, entry, colour) in enumerate(entries):
            spread = entry["tracking_error"]
            ax.bar(k, spread["mean"], color=colour, label=label,
                   yerr=[[spread["mean"] - spread["min"]], [spread["max"] - spread["mean"]]],
                   capsize=3)
        floor = result["dem_noise_floor"]["tracking_error"]["mean"]
        ax.axhline(floor + 0.02, color="tab:red", ls="--", lw=1, label="floor + 0.02 (target)")
        ax.set_xticks([])
        ax.set_ylabel("tracking error (mean TV per 30 s window) [-]")
        ax.set_title(scene)
        plotstyle.legend(ax, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.02), ncol=2)
    plotstyle.title(fig, "What the ROM's transport reaches with the DEM's own velocity field",
                    "bars: mean over (replica, ROM seed) against the other replicas, whiskers: "
                    "min-max; the replayed fields with the bulk at "
                    f"{next(iter(results.values()))['packing_density_kg_m2']:.1f} kg/m^2")
    fig.tight_layout()
    plotstyle.save(fig, path, dpi=110)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m surrogate.rom.transport_bound",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="exported held-out design folder")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--scene", action="append", default=None,
                        help="held-out scene, e.g. heldout_q2000 (repeatable; default all)")
    parser.add_argument("--half-window", action="append", type=float, default=None,
                        help="half window [s] of the DEM field's time mean, >= 0 (repeatable; "
                             "default 0, 15, 180)")
    parser.add_argument("--packing", action="append", default=None,
                        help=f"RomStorage's packing, one of {', '.join(PACKINGS)} (repeatable; "
                             "default none, avalanche)")
    parser.add_argument("--packing-density", type=float, default=None,
                        help="bulk density [kg/m^2] of the ROM with the DEM's field (default: "
                             "the DEM's mean settled density on the training design, "
                             "surrogate.rom.packing)")
    parser.add_argument("--landing-spread", action="append", type=float, default=None,
                        help="RomStorage's landing_spread [m], >= 0, of the ROM with the DEM's "
                             "field (repeatable; default 0)")
    parser.add_argument("--field", action="append", default=None,
                        help="field replayed: dem (the replica's own), modes:K (the "
                             "replica's projected on K POD modes of the training design's "
                             "velocities) or model (the fit at the replica's mass field) "
                             "(repeatable; default dem)")
    parser.add_argument("--rom-seeds", type=int, default=ROM_SEEDS,
                        help=f"ROM seeds 0 .. N-1 per run, 1-100 ({ROM_SEEDS})")
    parser.add_argument("--model", default=None,
                        help="ROM model file (default: the default ROM, "
                             "data/paper_rom_loose.npz)")
    args = parser.parse_args(argv)

    def progress(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    try:
        results = bound(args.data, args.scene, args.half_window or HALF_WINDOWS,
                        args.packing or PACKINGS_SCORED, args.rom_seeds, args.model,
                        args.packing_density, progress,
                        args.landing_spread or LANDING_SPREADS, args.field or FIELDS)
    except (ValidationError, OSError) as error:
        print(f"transport_bound: error: {error}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    jsonio.write(args.out / "transport_bound.json", results, indent=1)
    plot(results, args.out / "transport_bound.png")
    for scene, result in results.items():
        print(report(scene, result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
