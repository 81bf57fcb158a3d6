"""Hand-overs along the fidelity ladder during a run.

A stockpile whose model is chosen by accuracy (``cosim.fidelity``) changes
model when the running one leaves the range where its card holds: a ROM whose
inputs leave its training range, a pile nearly empty, a rate beyond what was
measured. ``hand_over`` moves the pile from one storage model to the next
exactly: the same particles (ids, masses, attributes: they never leave the
shared ``ParticleStore``), in the old model's order of leaving, at their x-y
positions when the old model had geometry, and the feeder's mass credit, so
that no kilogram is created, lost or delivered twice (``StorageModel.adopt``).

``Switcher`` applies a ``cosim.fidelity.Ladder`` step by step and keeps the
record of every switch (time, from, to, reason, particles handed over).
Positions go over in the stockpile's frame (x horizontal, y up, floor at
y = 0 under the outlet), which the ROM's container and the DEM's geometry of
one scene share.
"""

from __future__ import annotations

from dataclasses import asdict

import numpy as np

from cosim.fidelity import Ladder, OperatingPoint


def hand_over(old, new, t: float) -> np.ndarray:
    """Move the pile of storage model ``old`` to ``new`` (not yet bound) at
    ``t`` [s]; returns the ids handed over, in ``old``'s order of leaving.

    From a model with geometry the particles go over at their positions. From
    one without (FIFO, mixing) to one with, they are laid out by their order
    of leaving as the views draw such a pile (``cosim.stockpile_view.
    schematic_layout``: the next to leave nearest the outlet at x = 0, in a
    half disc holding the pile at ``new.bulk_areal_density()``), which the new
    model then settles (the DEM drops them to rest)."""
    from cosim.stockpile_view import schematic_layout

    ids = np.array(old.held_ids(), dtype=np.uint64)
    positions = None
    new.bind(old.particles, old.owner)
    if old.has_geometry and ids.size:
        positions = old.particles.position[old.particles.slots(ids), :2].copy()
    elif new.has_geometry and ids.size:
        held = float(old.particles.mass[old.particles.slots(ids)].sum())
        radius = np.sqrt(2.0 * held / (np.pi * new.bulk_areal_density()))
        x, y, _, _ = schematic_layout(ids, held, 0.0, radius)
        positions = np.column_stack((x, y))
    new.adopt(ids, t, positions=positions, credit_kg=old.feeder_credit_kg)
    return ids


class Switcher:
    """Which storage model runs, step by step, by a ``Ladder``.

    Parameters
    ----------
    ladder : cosim.fidelity.Ladder
        The cards and the target; ``ladder.start`` must have chosen the first model.
    build : callable
        ``build(model_name)`` -> a new, unbound storage model of that name.
    window_s : float
        Window of the tracking error the operating point is taken at [s] (30).
    rungs : list of str, optional
        The models from the cheapest up (default: the cards' order); a model's
        rung is its index, the time series of which model ran.
    """

    def __init__(self, ladder: Ladder, build, window_s: float = 30.0, rungs=None):
        self.ladder = ladder
        self.build = build
        self.window_s = float(window_s)
        self.rungs = list(rungs) if rungs is not None else [c.model for c in ladder.cards]
        self.switches: list[dict] = []

    def update(self, t: float, model, discharge_rate: float):
        """The model to step at ``t`` [s]: ``model`` itself, or its successor
        with the pile handed over. While the feeder stands still nothing leaves,
        so there is no outflow to track and nothing to decide."""
        if discharge_rate <= 0.0:
            return model
        point = OperatingPoint(throughput_kg_s=float(discharge_rate),
                               held_mass_kg=float(model.held_mass()), window_s=self.window_s)
        switch = self.ladder.update(t, point, out_of_range=model.out_of_range_now)
        if switch is None:
            return model
        successor = self.build(switch.to_model)
        ids = hand_over(model, successor, t)
        self.switches.append({**asdict(switch), "particles": int(ids.size),
                              "held_mass_kg": point.held_mass_kg,
                              "discharge_rate_kg_s": point.throughput_kg_s})
        return successor
