"""Vibrating screen: sends each parcel of ore to its undersize or oversize outlet.

Source: the ideal classifier of screening (King, "Modeling and Simulation of
Mineral Processing Systems", 2001, ch. 4: material finer than the aperture
passes, coarser material is retained), applied to the paper's pseudo-particles
(section "Digital twin as a distributed particle simulation": a pseudo-particle
is a parcel with an internal size distribution f_n over the 16 classes, and
keeps its identity through the plant).

Model. A parcel is not split (its id, and so its tracking history, stays
whole): a parcel whose mass fraction coarser than the aperture,
sum of f_n^k over the classes whose lower edge d_{k-1} >= ``aperture`` [m],
exceeds ``oversize_limit`` [-] leaves through ``oversize``, every other one
through ``undersize``. Parcels are screened at the screen's next step: the
same communication step for feeders listed before the screen, the next one
for a return leg listed after it (the deck holds nothing longer). In a closed circuit the
oversize goes to a crusher and comes back onto the screen; a crusher that
breaks everything coarser than the aperture closes the loop in one pass.

Events: "pass" per outlet (asset ``<name>_undersize``, ``<name>_oversize``).
Outputs ``undersize_kg``, ``oversize_kg``: mass sent through each outlet so far.
"""

from __future__ import annotations

import numpy as np

from cosim.assets import Asset, Plant
from cosim.kinds import AssetKind
from cosim.params import Parameters, Position, number
from cosim.sizes import DIAMETERS, RATIO

EMPTY_IDS = np.empty(0, dtype=np.uint64)


class Screen(Asset):
    """A screen deck of one aperture, two outlets.

    Parameters
    ----------
    name : str
        Asset name.
    plant : Plant
        The shared plant.
    location : (3,) array_like
        The feed end of the deck [m] (where both products leave, too).
    aperture : float
        Screen aperture [m] (default 0.1 m).
    oversize_limit : float
        Largest mass fraction coarser than the aperture that a parcel may hold
        and still pass as undersize [-] (default 0.05).
    """

    outlets = ("undersize", "oversize")
    output_names = ("undersize_kg", "oversize_kg")

    def __init__(self, name: str, plant: Plant, *, location, aperture: float = 0.1,
                 oversize_limit: float = 0.05):
        super().__init__(name, plant, location=location)
        self.aperture = float(aperture)
        self.oversize_limit = float(oversize_limit)
        lower_edges = DIAMETERS / RATIO
        self._coarse = lower_edges >= self.aperture * (1 - 1e-12)
        self._queue = EMPTY_IDS
        self._sent = {"undersize": 0.0, "oversize": 0.0}

    def _accept(self, ids: np.ndarray, t: float, inlet: str) -> None:
        self._queue = np.concatenate((self._queue, ids))

    def step(self, t: float, dt: float) -> None:
        if self._queue.size == 0:
            return
        ids, self._queue = self._queue, EMPTY_IDS
        store = self.particles
        slots = store.slots(ids)
        oversize = store.f[slots][:, self._coarse].sum(axis=1) > self.oversize_limit
        for outlet, chosen in (("undersize", ~oversize), ("oversize", oversize)):
            if chosen.any():
                self._sent[outlet] += float(store.mass[slots[chosen]].sum())
                self.plant.record("pass", f"{self.name}_{outlet}", t + dt, slots[chosen],
                                  self.location)
                self.send(outlet, ids[chosen], t + dt)

    def outputs(self) -> dict[str, float]:
        return {"undersize_kg": self._sent["undersize"], "oversize_kg": self._sent["oversize"]}


# ------------------------------------------------------------------ scenario kind
class ScreenParameters(Parameters):
    """``[assets.NAME] kind = "screen"``: see ``Screen``."""

    position_m: Position
    aperture_m: number(1e-5, 1.0, low_open=True, unit="m") = 0.1
    oversize_limit: number(0.0, 1.0) = 0.05


class ScreenKind(AssetKind):
    """A screen (``Screen``): inlet ``feed``, outlets ``undersize`` and ``oversize``."""

    Parameters = ScreenParameters
    component = Screen

    def build(self, name, p, context):
        screen = Screen(name, context.plant, location=p.position_m, aperture=p.aperture_m,
                        oversize_limit=p.oversize_limit)
        context.add(screen)
        return [screen]
