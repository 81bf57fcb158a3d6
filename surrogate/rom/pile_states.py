"""The paper's pile pictures at the paper's scale, from the shipped ROM stockpile.

Source: paper section "Simulator", figure "pile_states": the storage asset
(2,000 t, about 20,000 pseudo-particles, 60 m tall) at a pointy and at a
depleted state, particles of hardness 1 and 2 in blue and green; and section
"Integration test", figure "integration_test": in the granular surrogate the
particles of the surface layer (resolved DEM) are black, the others are
propagated by the reduced-order model and coloured by residence time.

The run (``run_states``): the shipped paper-scale ROM (``RomStorage``'s
default model, or the file the environment variable ``MINETWIN_ROM_MODEL`` names,
as for the feed prediction) with its DEM surface layer. Lots of ``doe.LOT_MASS`` (15 t)
alternate hardness 1 and 2 (``doe.LotFeed``, grade uniform in 0.2-0.8), split
into the training DEM's pseudo-particles (``emitter.split_lot``: 12-160 kg,
0.2-0.48 m).

1. The pile's earlier production: ``fill`` [kg] laid by the inlet
   (``StorageModel.prefill``, the sandpile rule), lot after lot, with entry
   times as if fed at ``FILL_RATE`` until t = 0.
2. Pointy state: inflow ``POINTY_INFLOW`` [kg/s] from the inlet with the
   feeder shut for ``pointy_s`` seconds: the cone grows under the inlet and
   the lots just released are still falling (black).
3. Depleted state: the feeder at ``DEPLETE_RATE`` [kg/s] (the paper's
   2 t/s) with ``DEPLETE_INFLOW`` [kg/s] from the inlet for ``deplete_s``
   seconds: the funnel above the outlet reaches the surface and a crater
   forms.

Figures: ``pile_states.png`` (both states by hardness) and
``pile_residence_time.png`` (both states by residence time [s] = now - the
time the particle entered the pile). ``summary.json`` gives each state's
held mass, particle count, surface height over the outlet and the inlet,
the surface particles, the share of the bulk hanging over emptied cells
(``surrogate.rom.hanging``), the mass balance and the ROM's inputs outside its
training ranges, the discharge commanded and the share of it delivered. Checks
(exit code 1 when one fails): mass balance, ids, a crater over the outlet, at least
``DELIVERED_SHARE`` of the commanded discharge delivered, and no state hanging more
than ``hanging.HANGING_LIMIT`` of its bulk over emptied cells.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from cosim import jsonio
from cosim.particles import ParticleStore
from surrogate.rom import doe

DESCRIPTION = ("the paper's pile states (pointy and depleted, by hardness) and the "
               "integration test's residence-time picture, from the shipped paper-scale ROM")

FILL_KG = 1_500_000.0
"""Mass laid before t = 0 [kg] (the integration test's pre-filled pile)."""
FILL_RATE = 2000.0
"""Rate the earlier production is dated at [kg/s] (the paper's largest)."""
POINTY_INFLOW = 1200.0
"""Inflow while the feeder is shut [kg/s] (the paper's 1.2 t/s)."""
DEPLETE_RATE = 2000.0
"""Feeder rate of the depleting phase [kg/s] (the paper's 2 t/s)."""
DEPLETE_INFLOW = 300.0
"""Inflow of the depleting phase [kg/s]."""
POINTY_S, DEPLETE_S = 60.0, 210.0
"""Seconds of each phase (``--quick``: ``QUICK_POINTY_S``, ``QUICK_DEPLETE_S``). The
depleted state ends at about 1.22 kt, just above the lightest pile the shipped ROM was
trained on (1.20 kt): drained further, the model extrapolates (measured: 420 s leaves
888 t, and the ROM reports ``held_mass`` outside its training range)."""
QUICK_POINTY_S, QUICK_DEPLETE_S = 20.0, 120.0
DELIVERED_SHARE = 0.99
"""Least share [-] of the commanded discharge the feeder must deliver: the depleted
pile still holds over 1.2 kt, so the DEM's feeder (Beverloo's law, up to
``max_discharge_rate`` 2 t/s) is never short of rock; the ROM's credit rule
delivers the setpoint to within one particle unless its bulk stops reaching the
feeder."""
OWNER = 0
HARDNESS_COLOURS = {1.0: "tab:blue", 2.0: "tab:green"}
"""The paper's colours of hardness 1 and 2."""


class _Feed:
    """Particles of the alternating lots, added to ``store`` as they are needed."""

    def __init__(self, store: ParticleStore, dem_config, seed: int):
        self.store, self.cfg = store, dem_config
        self.lots = doe.LotFeed(1, seed)
        self.rng = np.random.default_rng(seed + 1)

    def particles(self, mass: float, entry_time) -> np.ndarray:
        """Ids of new particles making up ``mass`` [kg]; ``entry_time(m)`` [s] dates the
        particle whose lot starts after ``m`` kg of this call."""
        from surrogate.dem.emitter import split_lot

        ids, done = [], 0.0
        for piece, tracking_id, grade, hardness in self.lots.take(mass):
            masses = split_lot(self.cfg, piece, self.rng)
            ids.append(self.store.add(mass=masses, f=doe.FEED_F, grade=grade,
                                      hardness=hardness, owner=OWNER,
                                      time=entry_time(done + np.cumsum(masses)),
                                      tracking_id=tracking_id))
            done += piece
        return np.concatenate(ids) if ids else np.empty(0, np.uint64)


def _state(store: ParticleStore, storage, t: float, name: str, dem_config) -> dict:
    """Positions, disk diameters (of ``dem_config``), hardness, residence time of the held
    particles, and which are falling."""
    ids = storage.held_ids()
    slots = store.slots(ids)
    falling = (np.isin(ids, storage.surface_dem.ids) if storage.surface_dem is not None
               else np.zeros(ids.size, bool))
    diameter = dem_config.diameter_of_mass(store.mass[slots])
    return {"name": name, "time": t, "x": store.position[slots, 0].copy(),
            "diameter": diameter,
            "y": store.position[slots, 1].copy(), "mass": store.mass[slots].copy(),
            "hardness": store.hardness[slots].copy(),
            "residence_time": t - store.time_in_owner[slots], "falling": falling}


def _surface_height(state: dict, x: float, half_width: float = 2.0) -> float:
    """Highest bulk particle within ``half_width`` [m] of ``x`` [m] (0 if none) [m]."""
    near = (np.abs(state["x"] - x) <= half_width) & ~state["falling"]
    return float(state["y"][near].max()) if near.any() else 0.0


def _hanging_share(state: dict, storage) -> float:
    """Share [-] of the state's bulk (the surface layer left out) hanging over emptied
    cells of the ROM's grid (``surrogate.rom.hanging``)."""
    from surrogate.rom.hanging import hanging_share_of

    bulk = ~state["falling"]
    return hanging_share_of(np.column_stack((state["x"][bulk], state["y"][bulk])),
                            state["mass"][bulk], storage.model.grid, storage.container)


def run_states(*, quick: bool = False, seed: int = 0, fill: float = FILL_KG,
               progress=None, model=None) -> tuple[list[dict], dict]:
    """The pointy and the depleted state (dicts of ``_state``) and the run's figures;
    ``model``: a ROM model file (default: ``RomStorage``'s default model)."""
    from surrogate.dem import DemConfig
    from surrogate.rom.storage import RomStorage

    storage = RomStorage(model, rng=np.random.default_rng(seed))
    store = ParticleStore(capacity=32_768)
    store.add_attribute("tracking_id", np.uint64, 0)
    storage.bind(store, OWNER)
    feed = _Feed(store, DemConfig.from_dict(storage.model.dem_config), seed)
    storage.prefill(feed.particles(fill, lambda m: (m - fill) / FILL_RATE), 0.0)
    phases = (("pointy", QUICK_POINTY_S if quick else POINTY_S, 0.0, POINTY_INFLOW),
              ("depleted", QUICK_DEPLETE_S if quick else DEPLETE_S, DEPLETE_RATE,
               DEPLETE_INFLOW))
    states, t, out_kg, in_kg, wall = [], 0.0, 0.0, 0.0, 0.0
    commanded_kg = sum(seconds * rate for _, seconds, rate, _ in phases)
    for name, seconds, rate, inflow in phases:
        for _ in range(int(round(seconds / doe.CONTROL_STEP))):
            new = feed.particles(inflow * doe.CONTROL_STEP, lambda m, t=t: np.full(m.size, t))
            in_kg += float(store.mass[store.slots(new)].sum())
            tic = time.perf_counter()
            storage.receive(new, t)
            leaving = storage.step(t, doe.CONTROL_STEP, rate)
            wall += time.perf_counter() - tic
            out_kg += float(store.mass[store.slots(leaving)].sum())
            store.remove(leaving)
            t += doe.CONTROL_STEP
            if progress is not None:
                progress(t)
        states.append(_state(store, storage, t, name, feed.cfg))
    held_ids = storage.held_ids()
    held = float(store.mass[store.slots(held_ids)].sum())
    c = storage.container
    run = {"seed": seed, "fill_kg": fill, "simulated_s": t, "rom_wall_s": round(wall, 3),
           "realtime_factor": round(t / wall, 1) if wall > 0 else None,
           "mass_in_kg": in_kg, "mass_out_kg": out_kg, "held_kg": held,
           "discharge_commanded_kg": commanded_kg,
           "discharge_delivered_share": out_kg / commanded_kg if commanded_kg > 0 else 1.0,
           "mass_balance_rel_error": abs(fill + in_kg - out_kg - held) / (fill + in_kg),
           "ids_held_equal_store": bool(np.array_equal(np.sort(held_ids),
                                                       np.sort(store.id[:len(store)]))),
           "out_of_training_range_now": list(storage.out_of_range_now),
           "states": {s["name"]: {"time_s": s["time"], "held_kg": float(s["mass"].sum()),
                                  "particles": int(s["x"].size),
                                  "falling_particles": int(s["falling"].sum()),
                                  "hanging_mass_share": _hanging_share(s, storage),
                                  "surface_over_outlet_m": _surface_height(s, c.outlet_x),
                                  "surface_over_inlet_m": _surface_height(s, c.inlet_x)}
                      for s in states}}
    return states, run


def plot(states: list[dict], out: Path, run: str) -> list[Path]:
    """``pile_states.png`` (by hardness) and ``pile_residence_time.png``: every particle a
    disk of its size; surface-layer particles black, as in the paper."""
    from matplotlib.collections import EllipseCollection
    from matplotlib.colors import ListedColormap
    from matplotlib.lines import Line2D

    from cosim import plotstyle

    plt = plotstyle.pyplot()
    paths = []
    oldest = max(float(s["residence_time"].max()) for s in states)
    falling = Line2D([], [], marker="o", ls="", color="k", label="surface layer (resolved DEM)")
    for stem, what in (("pile_states", "hardness"), ("pile_residence_time", "residence time")):
        fig, axes = plt.subplots(len(states), 1, figsize=(12, 4.4 * len(states)), squeeze=False,
                                 layout="constrained")
        for ax, s in zip(axes[:, 0], states):
            diameter = s["diameter"]
            if what == "hardness":
                values, cmap, limits = s["hardness"], ListedColormap(
                    list(HARDNESS_COLOURS.values())), (0.5, 2.5)
                handles = [Line2D([], [], marker="o", ls="", color=colour,
                                  label=f"hardness {value:g} [-]")
                           for value, colour in HARDNESS_COLOURS.items()]
            else:
                values, cmap, limits, handles = s["residence_time"], "viridis", (0.0, oldest), []
            disks = EllipseCollection(diameter, diameter, 0.0, units="x",
                                      offsets=np.column_stack((s["x"], s["y"])),
                                      offset_transform=ax.transData, cmap=cmap, linewidths=0)
            disks.set_array(np.where(s["falling"], np.nan, values))
            disks.set_clim(*limits)
            disks.set_cmap(disks.cmap.with_extremes(bad="k"))  # surface layer: black
            ax.add_collection(disks)
            if what == "residence time":
                fig.colorbar(disks, ax=ax, label="residence time [s]", shrink=0.9)
            ax.set_xlim(s["x"].min() - 1.0, s["x"].max() + 1.0)
            ax.set_ylim(0.0, max(float(s["y"].max()) + 1.0, 1.0))
            ax.set_title(f"{s['name']} state at t = {s['time']:.0f} s: "
                         f"{s['mass'].sum() / 1e3:,.0f} t in {s['x'].size:,} particles",
                         fontsize=10)
            ax.set_xlabel("x [m]")
            ax.set_ylabel("height y [m]")
            ax.set_aspect("equal")
            ax.grid(False)
            ax.legend(handles=handles + [falling], loc="upper right", fontsize=8)
        plotstyle.title(fig, f"Paper-scale ROM stockpile coloured by {what}", run)
        paths.append(plotstyle.save(fig, out / f"{stem}.png", dpi=100))
    return paths


def reproduce(out_dir, *, quick: bool = False, progress: bool = True, seed: int = 0):
    """Run, plot, write ``summary.json``; (summary, failed checks)."""
    from cosim.analyses.feed_prediction import rom_model_from_env
    from cosim.analyses.profile_run import output_folder
    from cosim.plotstyle import run_label
    from cosim.progress import Progress
    from surrogate.rom.hanging import HANGING_LIMIT

    model = rom_model_from_env()
    out = output_folder(out_dir)
    seconds = (QUICK_POINTY_S + QUICK_DEPLETE_S) if quick else (POINTY_S + DEPLETE_S)
    bar = Progress("pile states: ROM run", seconds) if progress else None
    try:
        states, summary = run_states(quick=quick, seed=seed, model=model,
                                     progress=None if bar is None else bar.update)
    finally:
        if bar is not None:
            bar.close()
    summary["quick"] = quick
    summary["model"] = str(model) if model else "shipped paper-scale"
    label = run_label(scenario="pile_states", seed=seed,
                      model=f"rom ({Path(model).name if model else 'shipped paper-scale'})")
    summary["figures"] = [p.name for p in plot(states, out, label)]
    pointy, depleted = summary["states"]["pointy"], summary["states"]["depleted"]
    failed = []
    if summary["mass_balance_rel_error"] > 1e-9:
        failed.append(f"mass balance {summary['mass_balance_rel_error']:.2e} > 1e-9")
    if not summary["ids_held_equal_store"]:
        failed.append("the held ids differ from the particles in the store")
    if not depleted["surface_over_outlet_m"] < pointy["surface_over_outlet_m"]:
        failed.append("no crater: the surface over the outlet did not sink while depleting")
    if summary["discharge_delivered_share"] < DELIVERED_SHARE:
        failed.append(f"the feeder delivered {summary['discharge_delivered_share']:.3f} of the "
                      f"{summary['discharge_commanded_kg'] / 1e3:,.0f} t commanded (at least "
                      f"{DELIVERED_SHARE}; the pile held enough for all of it)")
    for name, state in summary["states"].items():
        if state["hanging_mass_share"] > HANGING_LIMIT:
            failed.append(f"{name} state: {state['hanging_mass_share']:.4f} of the bulk hangs over "
                          f"emptied cells (at most {HANGING_LIMIT} rests on its base)")
    summary["checks_failed"] = failed
    jsonio.write(out / "summary.json", summary, indent=2, sort_keys=True)
    return summary, failed
