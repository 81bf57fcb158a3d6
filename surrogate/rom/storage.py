"""The ROM stockpile: bulk advected by the predicted velocity field.

Source: paper sections "Digital twin as a distributed particle simulation"
and "Integration test" (Wallin and Servin 2021): a low-dimensional model
predicts the pile's flow field from its mass distribution and the control
signals; bulk particles are advected by that field; incoming particles fall
and spread over the surface; particles reaching the outlet are removed and
reported with their ids, masses and attributes.

One step of ``dt`` [s] is split into substeps of at most ``max_step`` [s]:

1. every ``update_interval`` [s] (and whenever the discharge rate changes)
   the mass field M of the held particles is sampled on the model grid and
   the velocity field is predicted, v = ROM(M, q_out, q_in), with q_in the
   inflow rate [kg/s] averaged over the last ``inflow_window`` seconds (a
   model file fitted to the mass flux, ``RomModel(target="flux")``, gives
   its predicted flux over this M, floored: ``surrogate.rom.model``); the
   regressed field is not mass-conserving, so with ``transport="balanced"``
   (default) it is projected on the grid onto the nearest field that keeps
   the settled bulk at its density, with the feeder as its sink and the
   bulk's volume held (``surrogate.rom.transport``);
2. once ``move_interval`` [s] has passed since they last moved, particles
   are advected over that time by v (the projected face velocities,
   ``surrogate.rom.transport.advect_faces``; with ``transport="repack"`` the
   cell-centred prediction, ``surrogate.rom.advect``), take a random
   step of the bulk's dispersion about the mean flow, D = alpha |v| with
   the dispersivity alpha measured on the training DEM
   (``surrogate.rom.dispersion``), then the bulk is packed again
   (``packing``; default ``surrogate.rom.surface.settle``: angle-of-repose
   avalanches, columns re-stacked at the bulk density, which also takes up
   what the projection leaves to the surface cells);
3. the outlet: the feeder's mass credit grows by q_out * h and whole
   particles leave while their mass fits in the credit (the credit rule of
   ``cosim.storage.StorageModel``), so the discharged mass follows
   q_out * t to within one particle. As the DEM's belt feeder, it takes
   particles from its zone (``outlet_x +- outlet_width / 2``, up to
   ``feeder_zone_height`` above the floor), across the opening in
   proportion to the predicted field's downward speed over it (the DEM's
   draw is fastest over the middle of the opening, and the field is fitted
   to the DEM's; ``surrogate.rom.surface.feeder_take``); should the zone hold too
   little, the nearest particles to the outlet follow, with horizontal
   offsets weighted by ``FUNNEL_ASPECT`` (the column above the opening
   drains first, material beside it on the floor is the dead zone).

Incoming particles (``receive``) go to the surface layer. With
``surface="dem"`` (default) they are released at the inlet, fall and impact
on the bulk by resolved DEM (``surrogate.rom.surface_dem``; paper: "resolved
DEM is used" for the particles impacting the pile); after the impact they
roll on by the angle-of-repose rule from where they landed
(``surrogate.rom.surface.deposit``) and join the bulk. In each substep the
surface layer runs first, over the bulk as it stands. With
``surface="rule"`` they are placed at once by the sandpile rule alone (fall
under the inlet, angle-of-repose spreading) and join the bulk at once.

The particle store holds positions in the DEM plane: ``position[:, 0]`` = x
(horizontal), ``position[:, 1]`` = y (up) [m], ``position[:, 2]`` = 0;
``velocity[:, :2]`` is the interpolated field [m/s]. ``has_geometry`` tells
the views to show these as they are.

Parameters
----------
model : RomModel or str or Path, optional
    The trained model or its file (``minetwin rom train``), loaded by
    ``load``. Default: ``DEFAULT_MODEL``, the paper-scale ROM that ships with
    the package (the paper's 2 kt, 60 m pile; provenance in its header and
    ``surrogate/rom/README.md``, "Loose packing and three validation scenes").
update_interval : float
    Seconds between velocity predictions (default 1.0 s).
max_step : float
    Largest outlet/packing substep [s] (default 1.0 s; advection inside a
    substep is further split so no particle moves more than half a cell).
move_interval : float
    Least time between moves of the bulk [s] (default 1.0 s, the control
    step the ROM is trained and scored at, ``doe.CONTROL_STEP``): shorter
    steps add up and the bulk moves once their sum reaches it, while the
    outlet takes its particles every step. A mine stepping at 0.5 s so runs
    the bulk as ``minetwin rom evaluate`` scored it, at half the cost.
inflow_window : float
    Averaging window of the inflow-rate control signal [s] (default 30 s).
rng : numpy.random.Generator, optional
    Seeded generator of the surface layer (default seed 0).
fallback : {None, "dem"}
    What to do when an input leaves the training ranges (default None:
    warn and keep extrapolating). With ``"dem"`` the storage hands its pile
    over to the DEM at the first step that sees such an input and runs as
    ``surrogate.dem_storage.DemStorage`` from then on (``fallen_back_at``
    [s] tells when): every held particle becomes a DEM disk with the same
    id, mass, grade, hardness, size fractions and tracking id, at its x
    position and in its height order (``surrogate.rom.handover``: lifted
    just enough that no disks overlap), at rest; the feeder's mass credit
    carries over, so held and discharged mass and ids stay exact.
fallback_config : DemConfig or dict or str, optional
    The DEM of the fall-back (a ``DemConfig``, a dict of its fields or a
    TOML path); default the model's training DEM (``RomModel.dem_config``),
    else ``surrogate.rom.doe.training_config()``. Its floor must span the
    model's container.
surface : {"dem", "rule"}
    Surface layer (default "dem", see above).
surface_config : DemConfig or dict or str, optional
    The DEM of the surface layer (contact law, particle density and sizes,
    inlet height); default the model's training DEM (``RomModel.dem_config``),
    else ``surrogate.rom.doe.training_config()``.
surface_dt_safety_factor : float, optional
    Surface-layer time step = contact time / this (default: the surface
    DEM's own ``dt_safety_factor``; see ``surrogate.rom.surface_dem``).
transport : {"balanced", "projected", "repack"}
    Bulk transport (default "balanced"): the predicted field projected onto a
    mass-conserving one (``surrogate.rom.transport.project``) whose free
    surface carries the predicted inward flux scaled so the bulk keeps its
    volume ("balanced", ``free_surface="flux"``) or is held at potential 0
    ("projected", ``free_surface="potential"``); "repack": the prediction as
    it is, the packing undoing its compaction (the scheme before the
    projection). On the paper-scale held-out scenes: surrogate/rom/README.md.
packing : {"avalanche", "column", "loose", "none"}, optional
    After each move: ``settle`` with angle-of-repose avalanches, ``settle``
    without them (columns re-stacked in their height order), ``settle_loose``
    (voids close, the field's spacing stays; avalanches on the real tops) or
    nothing (default None: the model's ``storage_settings``, else "avalanche").
void_gap : float, optional
    With ``packing="loose"``: the largest void [m] a particle may keep over the
    stack below it (``surface.settle_loose``; default None: the model's
    ``storage_settings``, else ``VOID_GAP``).
fill : float
    Least fraction of a full cell's mass that makes a grid cell bulk in the
    projection [-] (default ``surrogate.rom.transport.FILL`` = 0.9).
relax : float
    Fraction of the way to its packed height a particle moves at each
    packing (default 1, in (0, 1]; ``settle``'s ``relax``).
velocity_model : {"regressed", "kinematic", "hybrid"}
    The field the bulk moves by, before the transport makes it
    mass-conserving (default "regressed"): the model's POD/ridge prediction
    from the mass field and the rates, the kinematic funnel flow of
    Nedderman and Tuzun (1979) above the feeder for its discharge rate
    (``surrogate.rom.kinematic``; the model's training ranges are still
    checked), or "hybrid": the regression with its downward speed raised to
    the kinematic one where that is faster, above the feeder's zone
    (``surrogate.rom.kinematic.hybrid_field``).
    On the paper-scale held-out scenes: surrogate/rom/README.md.
diffusion_length : float
    The kinematic model's diffusion length B [m] (default
    ``surrogate.rom.kinematic.DIFFUSION_LENGTH`` = 1.06 m, fitted on the
    paper-scale training design); used with ``velocity_model="kinematic"`` or
    ``"hybrid"``.
packing_density : float, optional
    Areal density [kg/m^2] the ROM packs its bulk at (default None: the model's
    ``storage_settings``, else the model container's ``areal_density``, the 90th
    percentile of the base pile's cell masses, ``doe.areal_density``). Given, the
    storage runs in a copy of the container with this density, so everything
    that uses the bulk density uses it: the column packing and avalanches
    (``surface.settle``), the surface heights and deposits
    (``surface.surface_heights``, ``deposit``), the packing columns' width
    (``surface.column_width``), the projection's bulk cells (``fill`` times a
    full cell) and its feeder outflow q_out / rho_A (``transport.project``), the
    kinematic field's flux and ``bulk_areal_density``. The model's regression
    keeps its own container (``RomModel.full_cell_mass``, part of the fit). The
    DEM's mean settled density on a training design:
    ``surrogate.rom.packing.settled_density`` (paper design: 564.2 kg/m^2, 0.908
    of 621.1; surrogate/rom/README.md, "Packing at the DEM's mean settled
    density").
rest_fraction : float or None
    Share [-] of the feeder's mean outlet speed q_out / (rho_A W) below which
    a cell of the predicted field is at rest (its velocity 0) before the
    transport (``surrogate.rom.rest``; default None: the model file's
    ``rest_fraction``, fitted at ``minetwin rom train``, 0.08 for the shipped
    paper-scale ROM and 0, off, for a model of a point outlet; 0 turns it off).
    On the paper-scale held-out scenes: surrogate/rom/README.md, "The resting
    bulk".
landing_spread : float, optional
    Standard deviation [m] of a normal offset added to the x where the surface
    DEM leaves each particle, before it rolls on by the angle-of-repose rule
    (default None: the model's ``storage_settings``, else 0: none; used with
    ``surface="dem"``). The surface layer's fixed
    bed takes no part in the crowding of a dense stream, so on the paper-scale
    pile its particles join the bulk closer to the inlet than the DEM's do
    when they reach the bulk age ``doe.BULK_AGE``: measured on the training
    design's two base piles at 1.2-2 t/s in and out, the DEM's newcomers need
    a normal offset of 2.89 m (2.45-3.23 m over four measurements,
    ``surrogate.rom.landing``) on top of where the surface layer puts them
    (surrogate/rom/README.md, "Where the inflow joins the bulk").
"""

from __future__ import annotations

import warnings
from collections import deque
from dataclasses import replace
from pathlib import Path

import numba
import numpy as np

from cosim.errors import ValidationError, check_finite_range
from cosim.storage import StorageModel, budget_shares, check_discharge_rate
from surrogate.rom import doe
from surrogate.rom.advect import advect, interpolate, write_positions
from surrogate.rom.dispersion import disperse
from surrogate.rom.grid import mass_field, mean_field
from surrogate.rom.handover import drop_heights
from surrogate.rom.kinematic import DIFFUSION_LENGTH, hybrid_field
from surrogate.rom.kinematic import velocity_field as kinematic_field
from surrogate.rom.model import OutOfTrainingRange, RomModel
from surrogate.rom.rest import at_rest, check_share
from surrogate.rom.surface import (column_width, deposit, feeder_take, settle, settle_loose,
                                   surface_heights)
from surrogate.rom.surface_dem import SurfaceDem
from surrogate.rom.transport import FILL, advect_faces, centred, project

FIXED_GRID_MODEL = Path(__file__).parent / "data" / "paper_rom.npz"
"""The shipped fixed-grid paper-scale ROM (``minetwin rom train`` on the committed paper
design, chosen by leave-one-run-out velocity error; the command that regenerates it is in
its header's ``provenance``). The diagnostics that study the fixed grid's basis name it."""

REGISTERED_MODEL = Path(__file__).parent / "data" / "paper_rom_registered.npz"
"""A shipped option: the registered fit chosen by tracking on the validation scene
(``minetwin rom train --registration height --validation ...``; its storage settings:
no packing at the design's settled density, landing spread 2.9 m; the regenerating
command in its ``provenance``; surrogate/rom/README.md, "Chosen on the validation
scene"). Without packing its drained pile leaves bulk hanging over emptied cells
(surrogate/rom/README.md, "The pile the option builds")."""

LOOSE_MODEL = Path(__file__).parent / "data" / "paper_rom_loose.npz"
"""The registered fit (``minetwin rom train --registration height``) under the loose
packing (``surface.settle_loose``, void gap 0.3 m), chosen on the four validation
scenes by its largest excess over a scene's DEM noise floor (``--select-by
floor-excess``, three DEM replicas per scene) among fits whose bulk rests on its base
(the regenerating command in its ``provenance``; surrogate/rom/README.md, "Loose
packing and three validation scenes", "A third replica per validation scene" and "A
second pile at 2 t/s")."""

DEFAULT_MODEL = LOOSE_MODEL
"""The ROM a stockpile runs when no model file is named: of the shipped files, the one
that tracks best on the validation scenes and on every held-out scene with its piles
resting on their base (surrogate/rom/README.md, "Loose packing and three validation
scenes")."""


def load_model(model=None) -> RomModel:
    """The model file ``model`` names (a path), or ``DEFAULT_MODEL`` when it names none:
    what the tools that study a ROM load, so that they study the one a stockpile runs."""
    return RomModel.load(model or DEFAULT_MODEL)


RANGE_CHECK_INTERVAL = 10.0
"""Seconds between checks of the ROM inputs against the training ranges."""

FUNNEL_ASPECT = 3.0
"""Weight of horizontal offsets in the outlet's order of leaving [-]."""

FALLBACKS = (None, "dem")
"""Accepted values of ``RomStorage(fallback=...)``."""

SURFACES = ("dem", "rule")
"""Accepted values of ``RomStorage(surface=...)``."""

TRANSPORTS = ("repack", "projected", "balanced")
"""Accepted values of ``RomStorage(transport=...)``."""

PACKINGS = ("avalanche", "column", "loose", "none")
"""Accepted values of ``RomStorage(packing=...)``."""

DEFAULT_PACKING = "avalanche"
"""The packing of a model whose ``storage_settings`` name none."""

VOID_GAP = 0.3
"""``void_gap`` [m] of a model whose ``storage_settings`` name none."""

VELOCITY_MODELS = ("regressed", "kinematic", "hybrid")
"""Accepted values of ``RomStorage(velocity_model=...)``."""


@numba.njit(cache=True)
def _compact(keep, ids, mass, position):
    """Move the rows ``keep`` retains to the front, in order; returns their count."""
    kept = 0
    for p in range(keep.size):
        if keep[p]:
            ids[kept] = ids[p]
            mass[kept] = mass[p]
            position[kept, 0] = position[p, 0]
            position[kept, 1] = position[p, 1]
            kept += 1
    return kept


@numba.njit(cache=True)
def _renumbered(order, keep):
    """A stacking order over the particles ``keep`` retains, in their new numbering."""
    number = np.empty(keep.size, np.int64)
    kept = 0
    for p in range(keep.size):
        number[p] = kept
        kept += keep[p]
    out = np.empty(kept, np.int64)
    k = 0
    for p in order:
        if keep[p]:
            out[k] = number[p]
            k += 1
    return out


def _dem_config(config):
    """A ``DemConfig`` from a config, a dict of its fields or a TOML path (None: the
    training stockpile, ``doe.training_config()``)."""
    from surrogate.dem import DemConfig

    if config is None:
        return doe.training_config()
    if isinstance(config, dict):
        return DemConfig.from_dict(config)
    if isinstance(config, (str, Path)):
        return DemConfig.from_toml(str(config))
    return config


class RomStorage(StorageModel):
    """Reduced-order stockpile model behind the storage interface (see module docstring)."""

    name = "rom"
    has_geometry = True
    checkpointable = True
    default_model_file = DEFAULT_MODEL

    def __init__(self, model=None, *, update_interval: float = 1.0, max_step: float = 1.0,
                 move_interval: float = doe.CONTROL_STEP, inflow_window: float = 30.0,
                 rng: np.random.Generator | None = None,
                 fallback: str | None = None, fallback_config=None, surface: str = "dem",
                 surface_config=None, surface_dt_safety_factor: float | None = None,
                 transport: str = "balanced", packing: str | None = None, fill: float = FILL,
                 relax: float = 1.0, velocity_model: str = "regressed",
                 diffusion_length: float = DIFFUSION_LENGTH,
                 packing_density: float | None = None,
                 rest_fraction: float | None = None, landing_spread: float | None = None,
                 void_gap: float | None = None):
        super().__init__(rng=rng)
        # packing, packing_density, landing_spread and void_gap left None take the
        # model's storage_settings (the ones it was chosen under) at load
        self.void_gap_option = (None if void_gap is None else float(
            check_finite_range("void_gap", void_gap, 0.0, unit="m")))
        self.landing_spread_option = (None if landing_spread is None else float(
            check_finite_range("landing_spread", landing_spread, 0.0, unit="m")))
        self.rest_option = (None if rest_fraction is None else float(check_finite_range(
            "rest_fraction", rest_fraction, 0.0, 1.0)))
        self.rest_fraction = 0.0  # the share in use: the option's, else the model's
        self.packing_density_option = (None if packing_density is None else float(
            check_finite_range("packing_density", packing_density, 0.0, low_open=True,
                               unit="kg/m^2")))
        if velocity_model not in VELOCITY_MODELS:
            raise ValidationError("velocity_model", f"one of {VELOCITY_MODELS}",
                                  f"got {velocity_model!r}")
        self.velocity_model = velocity_model
        self.diffusion_length = float(check_finite_range("diffusion_length", diffusion_length,
                                                         0.0, low_open=True, unit="m"))
        if transport not in TRANSPORTS:
            raise ValidationError("transport", f"one of {TRANSPORTS}", f"got {transport!r}")
        if packing is not None and packing not in PACKINGS:
            raise ValidationError("packing", f"one of {PACKINGS}", f"got {packing!r}")
        self.transport, self.packing_option = transport, packing
        self.fill = float(check_finite_range("fill", fill, 0.0, 1.0, low_open=True))
        self.relax = float(check_finite_range("relax", relax, 0.0, 1.0, low_open=True))
        self._faces = None  # the projected face velocities (any transport but "repack")
        if fallback not in FALLBACKS:
            raise ValidationError("fallback", f"one of {FALLBACKS}", f"got {fallback!r}")
        if surface not in SURFACES:
            raise ValidationError("surface", f"one of {SURFACES}", f"got {surface!r}")
        self.surface = surface
        self.surface_config = surface_config
        self.surface_dt_safety_factor = surface_dt_safety_factor
        self.surface_dem: SurfaceDem | None = None
        self.fallback = fallback
        self.fallback_config = fallback_config
        self.dem_storage = None
        self.fallen_back_at: float | None = None
        self.update_interval = float(check_finite_range(
            "update_interval", update_interval, 0.0, low_open=True, unit="s"))
        self.max_step = float(check_finite_range("max_step", max_step, 0.0, low_open=True,
                                                 unit="s"))
        self.move_interval = float(check_finite_range("move_interval", move_interval, 0.0,
                                                      unit="s"))
        self._unmoved = 0.0  # seconds since the bulk last moved
        self._bulk_in_store = False  # the store holds the bulk's positions and velocities
        self.inflow_window = float(check_finite_range("inflow_window", inflow_window, 0.0,
                                                      low_open=True, unit="s"))
        self.model: RomModel | None = None
        self._ids = np.empty(0, dtype=np.uint64)
        self._mass = np.empty(0)
        self._pos = np.empty((0, 2))
        self._order = np.empty(0, dtype=np.int64)  # the bulk's stacking order (settle's hint)
        self._receipts: deque[tuple[float, float]] = deque()
        self._field = None
        self._field_time = -np.inf
        self._field_rate = None
        self._width = None
        self._drained = None
        self.out_of_range: dict[str, str] = {}
        self.out_of_range_now: tuple[str, ...] = ()
        self._next_range_check = -np.inf
        self.load(DEFAULT_MODEL if model is None else model)

    # ------------------------------------------------------------ set-up
    def load(self, model) -> "RomStorage":
        """Use a trained ``RomModel``, or load one from its file (``minetwin rom train``).

        Nothing is fitted here: training is ``RomModel.fit``.
        """
        if isinstance(model, (str, Path)):
            model = RomModel.load(model)
        elif not isinstance(model, RomModel):
            raise ValidationError("model", "a RomModel or the path of a ROM model file",
                                  f"got {type(model).__name__}")
        if model.container is None or not model.trained:
            raise ValidationError("model", "a trained ROM with its container geometry")
        self.model = model
        settings = model.storage_settings
        self.packing = (settings.get("packing", DEFAULT_PACKING) if self.packing_option is None
                        else self.packing_option)
        self.packing_density = (settings.get("packing_density")
                                if self.packing_density_option is None
                                else self.packing_density_option)
        self.landing_spread = (settings.get("landing_spread", 0.0)
                               if self.landing_spread_option is None
                               else self.landing_spread_option)
        self.void_gap = (settings.get("void_gap", VOID_GAP) if self.void_gap_option is None
                         else self.void_gap_option)
        self.container = (model.container if self.packing_density is None else
                          replace(model.container, areal_density=self.packing_density))
        self.rest_fraction = (model.rest_fraction if self.rest_option is None
                              else self.rest_option)
        check_share(self.rest_fraction, self.container)  # here, not at a run's first discharge
        if self.surface == "dem":
            self.surface_dem = SurfaceDem(_dem_config(self.surface_config or model.dem_config),
                                          self.container, self.surface_dt_safety_factor,
                                          rng=self.rng)
        return self

    # ------------------------------------------------------------ inflow
    def receive(self, ids, t: float) -> None:
        """Particles arriving at the inlet enter the surface layer (module docstring)."""
        if self.dem_storage is not None:
            return self.dem_storage.receive(ids, t)
        ids = np.asarray(ids, dtype=np.uint64)
        if ids.size == 0:
            return
        slots = self.particles.slots(ids)
        mass = self.particles.mass[slots].copy()
        width = self._column_width(mass)
        if self.surface_dem is not None:
            self.particles.position[slots, :2] = self.surface_dem.add(ids, mass)
            self.particles.position[slots, 2] = 0.0
        else:
            heights = surface_heights(self.container, width, self._pos, self._mass)
            self._append(ids, mass, deposit(self.container, width, heights, mass, self.rng))
        self._receipts.append((float(t), float(mass.sum())))

    def prefill(self, ids, t: float) -> None:
        """The pile's earlier production (``StorageModel.prefill``): laid at once by
        the sandpile rule, under the inlet at the angle of repose (the pile the
        inlet builds, settled), not dropped through the surface layer, and not
        counted in the inflow rate the model is fed."""
        if self.dem_storage is not None:
            return self.dem_storage.prefill(ids, t)
        ids = np.asarray(ids, dtype=np.uint64)
        if ids.size == 0:
            return
        mass = self.particles.mass[self.particles.slots(ids)].copy()
        width = self._column_width(mass)
        heights = surface_heights(self.container, width, self._pos, self._mass)
        self._append(ids, mass, deposit(self.container, width, heights, mass, self.rng))

    def _land(self, ids, mass, position, heights) -> None:
        """Particles whose impact the surface DEM resolved roll on from where it
        left them by the angle-of-repose rule, then join the bulk (``heights``:
        the bulk's surface, which the surface DEM's bed was laid on)."""
        if ids.size:
            landing_x = position[:, 0]
            if self.landing_spread > 0.0:  # no draw at 0: runs without it stay as they were
                landing_x = np.clip(landing_x + self.landing_spread
                                    * self.rng.standard_normal(ids.size),
                                    self.container.x_min, np.nextafter(self.container.x_max,
                                                                       -np.inf))
            self._append(ids, mass, deposit(self.container, self._width, heights, mass,
                                            self.rng, landing_x=landing_x))

    def bulk_areal_density(self) -> float:
        return float(self.container.areal_density)

    def adopt(self, ids, t: float, *, positions=None, credit_kg: float = 0.0) -> None:
        """A hand-over (``StorageModel.adopt``): with positions (from a DEM or
        another ROM, in this container's frame) the pile is placed as it lay;
        without, received at the inlet."""
        if positions is None:
            self.receive(ids, t)
        else:
            self.place(ids, positions)
        self._credit_kg = float(credit_kg)

    def place(self, ids, position) -> None:
        """Particles already resting in the pile at ``position`` (N, 2) [m] (initial state)."""
        if self.dem_storage is not None:
            raise ValidationError("place", "calls before the hand-over to the DEM",
                                  f"the storage runs as DEM since t = {self.fallen_back_at} s")
        ids = np.asarray(ids, dtype=np.uint64)
        position = np.asarray(position, dtype=np.float64).reshape(-1, 2)
        if position.shape[0] != ids.size:
            raise ValidationError("position", f"{ids.size} rows of (x, y)",
                                  f"got {position.shape[0]}")
        check_finite_range("position", position, unit="m")
        mass = self.particles.mass[self.particles.slots(ids)].copy()
        self._column_width(mass)
        self._append(ids, mass, position)

    def _column_width(self, mass) -> float:
        """Surface/packing column width, fixed by the first particles (about one particle)."""
        if self._width is None and len(mass):
            self._width = column_width(self.container, float(np.median(mass)))
            columns = max(int(round((self.container.x_max - self.container.x_min)
                                    / self._width)), 1)
            self._drained = np.zeros(columns)
        return self._width

    def _append(self, ids, mass, position) -> None:
        self._order = np.concatenate((self._order, np.arange(self._ids.size,
                                                             self._ids.size + len(ids))))
        self._ids = np.concatenate((self._ids, ids))
        self._mass = np.concatenate((self._mass, mass))
        self._pos = np.concatenate((self._pos, position))
        slots = self.particles.slots(ids)
        if self._field is not None:
            g = self.model.grid
            write_positions(self._field, g.x_min, g.y_min, g.dx, g.dy,
                            np.ascontiguousarray(position, dtype=np.float64), slots,
                            self.particles.position, self.particles.velocity)
        else:
            self.particles.position[slots, :2] = position
            self.particles.position[slots, 2] = 0.0

    def inflow_rate(self, t: float) -> float:
        """Inflow control signal [kg/s]: mass received in the last ``inflow_window`` s."""
        while self._receipts and self._receipts[0][0] <= t - self.inflow_window:
            self._receipts.popleft()
        return sum(m for _, m in self._receipts) / self.inflow_window

    # ------------------------------------------------------------ flow
    def velocity_field(self, t: float, discharge_rate: float) -> np.ndarray:
        """Predicted velocity field [m/s] ``(ny, nx, 2)`` for the current mass distribution.

        Every ``RANGE_CHECK_INTERVAL`` seconds the inputs are checked against
        the training ranges; each input found outside is warned once
        (``OutOfTrainingRange``) and its message kept in ``out_of_range``;
        ``out_of_range_now`` names the inputs outside at the latest check.
        """
        return self._predicted(t, discharge_rate, mass_field(self.model.grid, self._pos,
                                                             self._mass))

    def _predicted(self, t: float, discharge_rate: float, mass: np.ndarray) -> np.ndarray:
        """``velocity_field`` for the mass field ``mass`` (ny, nx) [kg] of the held bulk."""
        model = self.model
        inflow = self.inflow_rate(t)
        if t >= self._next_range_check or discharge_rate != self._field_rate:
            self._next_range_check = t + RANGE_CHECK_INTERVAL
            found = model.check_ranges(mass, discharge_rate, inflow, model.mass_residual(mass),
                                       warn=False)
            self.out_of_range_now = tuple(sorted(found))
            for name, message in found.items():
                if name not in self.out_of_range:
                    self.out_of_range[name] = message
                    warnings.warn(message, OutOfTrainingRange, stacklevel=4)
        return self.predicted_field(mass, discharge_rate, inflow)

    def predicted_field(self, mass: np.ndarray, discharge_rate: float,
                        inflow_rate: float) -> np.ndarray:
        """The field [m/s] (ny, nx, 2) of ``velocity_model`` for the mass field ``mass``
        (ny, nx) [kg] and the rates [kg/s], before the transport projects it (no
        range check)."""
        if self.velocity_model == "regressed":
            field = self.model.predict(mass, discharge_rate, inflow_rate, check=False,
                                       areal_density=self.bulk_areal_density())
        else:
            kinematic = kinematic_field(self.model.grid, self.container, discharge_rate,
                                        self.diffusion_length)
            field = kinematic if self.velocity_model == "kinematic" else hybrid_field(
                self.model.predict(mass, discharge_rate, inflow_rate, check=False,
                                   areal_density=self.bulk_areal_density()),
                kinematic, self.model.grid, self.container)
        return at_rest(field, discharge_rate, self.container, self.rest_fraction)

    def _refresh_field(self, t: float, rate: float):
        """The flow ``(field, faces)``, predicted again every ``update_interval`` or on
        a new rate (``faces``: the projected face velocities, None with
        ``transport="repack"``; otherwise ``field`` is their cell-centred mean)."""
        if (self._field is None or t - self._field_time >= self.update_interval - 1e-9
                or rate != self._field_rate):
            mass = mass_field(self.model.grid, self._pos, self._mass)
            self._field = self._predicted(t, rate, mass)
            if self.transport != "repack":
                self._faces = self._project(self._field, mass, rate)
                self._field = centred(*self._faces)
            self._field_time, self._field_rate = t, rate
            self._bulk_in_store = False
        return self._field, self._faces

    def _project(self, field, mass, rate: float):
        """The mass-conserving face velocities nearest to ``field`` (``transport``),
        the feeder drawing across its opening by the field's downward speed in the
        bottom row."""
        draw = np.maximum(-field[0, :, 1], 0.0)
        return project(field, mass, self.model.grid, self.container, rate, draw, self.fill,
                       free_surface="flux" if self.transport == "balanced" else "potential")

    def _keep(self, keep: np.ndarray) -> None:
        """Keep the bulk particles where ``keep`` is true (in their order)."""
        kept = _compact(keep, self._ids, self._mass, self._pos)
        self._ids, self._mass, self._pos = self._ids[:kept], self._mass[:kept], self._pos[:kept]
        self._order = _renumbered(self._order, keep)

    def _move(self, flow, h: float, position: np.ndarray, mass: np.ndarray,
              dispersion: bool = True, hint=None) -> np.ndarray:
        """Advect ``position`` in place by ``flow`` (``_refresh_field``'s ``(field,
        faces)``) over ``h`` [s], let it disperse about the mean flow
        (``surrogate.rom.dispersion``, the model's measured dispersivity; left out
        with ``dispersion=False``), then pack the bulk (``packing``). Returns the
        stacking order (``settle``; ``hint``: the previous one)."""
        grid, c = self.model.grid, self.container
        field, faces = flow
        # substeps keep each move below half a cell (CFL-like)
        if faces is None:
            speed = np.abs(field).max()
        else:
            speed = max(np.abs(faces[0]).max(), np.abs(faces[1]).max())
        substeps = max(1, int(np.ceil(h * speed / (0.5 * min(grid.dx, grid.dy)))))
        if faces is None:
            advect(position, field, grid.x_min, grid.y_min, grid.dx, grid.dy, h, substeps,
                   c.x_min, c.x_max, c.floor)
        else:
            advect_faces(position, faces[0], faces[1], grid.x_min, grid.y_min, grid.dx,
                         grid.dy, h, substeps, c.x_min, c.x_max, c.floor)
        if dispersion:
            disperse(position, field, grid, self.model.dispersivity, h, self.rng,
                     c.x_min, c.x_max, c.floor)
        if self.packing == "none":
            return hint
        if self.packing == "loose":
            return settle_loose(c, self._width, position, mass, self.void_gap, hint=hint)
        return settle(c, self._width, position, mass, hint=hint,
                      sweeps=20 if self.packing == "avalanche" else 0, relax=self.relax)

    def _nearest_first(self, position, count_hint: int) -> np.ndarray:
        c = self.container
        height = position[:, 1] - c.floor
        offset = np.abs(position[:, 0] - c.outlet_x)
        in_zone = (offset <= 0.5 * c.outlet_width) & (height <= c.feeder_zone_height)
        # zone particles (key = height < zone height) before all others (key >= 1e6)
        d2 = np.where(in_zone, height, 1e6 + (FUNNEL_ASPECT * offset) ** 2 + height ** 2)
        if count_hint < d2.size:
            part = np.argpartition(d2, count_hint)[: count_hint + 1]
            return part[np.argsort(d2[part], kind="stable")]
        return np.argsort(d2, kind="stable")

    def _draw_weights(self, columns: int):
        """The feeder's draw per packing column: the predicted field's downward speed
        [m/s] at the column's centre, half the feeder zone above the floor (None,
        i.e. even, before a field is predicted or where it has no downward flow)."""
        if self._field is None:
            return None
        c, g = self.container, self.model.grid
        width = (c.x_max - c.x_min) / columns
        centre = np.empty((columns, 2))
        centre[:, 0] = c.x_min + (np.arange(columns) + 0.5) * width
        centre[:, 1] = c.floor + 0.5 * c.feeder_zone_height
        down = np.maximum(-interpolate(self._field, g.x_min, g.y_min, g.dx, g.dy, centre)[:, 1],
                          0.0)
        opening = np.abs(centre[:, 0] - c.outlet_x) <= 0.5 * c.outlet_width
        return down if down[opening].sum() > 0 else None

    def _take(self, position, mass, credit: float, drained=None) -> tuple[np.ndarray, float]:
        """Indices of the whole particles the feeder takes with ``credit`` [kg]."""
        drained = self._drained if drained is None else drained
        if self.container.outlet_width > 0:
            taken, credit = feeder_take(self.container, self._width, position, mass, drained,
                                        credit, self._draw_weights(drained.size))
            if taken.size or credit < mass.min():
                return taken, credit
        hint = min(int(credit / max(mass.min(), 1e-300)) + 1, mass.size)
        order = self._nearest_first(position, hint)
        count = int(np.searchsorted(np.cumsum(mass[order]), credit, side="right"))
        return order[:count], credit - float(mass[order[:count]].sum())

    def step(self, t: float, dt: float, discharge_rate: float) -> np.ndarray:
        """Advance ``dt`` [s]; return the ids that leave through the outlet, in order."""
        rate = check_discharge_rate(discharge_rate)
        dt = float(check_finite_range("dt", dt, 0.0, unit="s"))
        if self.fallback == "dem" and self.dem_storage is None and self._ids.size:
            self._refresh_field(t, rate)
            if self.out_of_range:
                self._hand_over_to_dem(t)
        if self.dem_storage is not None:
            return self.dem_storage.step(t, dt, rate)
        substeps = max(1, int(np.ceil(dt / self.max_step)))
        h = dt / substeps
        leaving = []
        for k in range(substeps):
            if self.surface_dem is not None and self.surface_dem.ids.size:
                heights = surface_heights(self.container, self._width, self._pos, self._mass)
                self._land(*self.surface_dem.advance(h, self._width, self._pos, self._mass,
                                                     heights), heights)
            if self._ids.size == 0:
                self._credit_kg, self._unmoved = 0.0, 0.0
                continue
            self._unmoved += h
            if self._unmoved >= self.move_interval - 1e-9:
                self._order = self._move(self._refresh_field(t + k * h, rate), self._unmoved,
                                         self._pos, self._mass, hint=self._order)
                self._unmoved, self._bulk_in_store = 0.0, False
            self._credit_kg += rate * h
            taken, self._credit_kg = self._take(self._pos, self._mass, self._credit_kg)
            if taken.size:
                leaving.append(self._ids[taken])
                keep = np.ones(self._ids.size, dtype=bool)
                keep[taken] = False
                self._keep(keep)
        self._write_back()
        return np.concatenate(leaving) if leaving else np.empty(0, dtype=np.uint64)

    def _write_back(self) -> None:
        """Positions and velocities into the particle store (sensors, monitor): the
        field's velocity for the bulk, the DEM's for the surface layer. The bulk is
        written when it has moved or its field changed since it was last written (the
        particles joining it are written as they join)."""
        if not self._bulk_in_store and self._ids.size:
            slots = self.particles.slots(self._ids)
            if self._field is not None:
                g = self.model.grid
                write_positions(self._field, g.x_min, g.y_min, g.dx, g.dy, self._pos, slots,
                                self.particles.position, self.particles.velocity)
            else:
                self.particles.position[slots, :2] = self._pos
                self.particles.position[slots, 2] = 0.0
            self._bulk_in_store = True
        free = self.surface_dem
        if free is not None and len(free):
            slots = self.particles.slots(free.ids)
            self.particles.position[slots, :2] = free.pos
            self.particles.position[slots, 2] = 0.0
            self.particles.velocity[slots, :2] = free.vel

    def _hand_over_to_dem(self, t: float) -> None:
        """Continue as DEM from time ``t`` (see ``fallback`` in the module docstring)."""
        from surrogate.dem import Dem
        from surrogate.dem_storage import DemStorage

        config = _dem_config(self.fallback_config or self.model.dem_config)
        c = self.container
        half = 0.5 * config.floor_width
        # the DEM's floor is y = 0 centred on x = 0: the ROM's container must lie on it
        if not (half >= max(-c.x_min, c.x_max) - 1e-9 and config.outlets and c.floor == 0.0):
            raise ValidationError("fallback_config", f"a DEM whose floor (y = 0) spans the "
                                  f"container [{c.x_min:g}, {c.x_max:g}] m and has an outlet",
                                  f"got floor_width {config.floor_width:g} m, container floor "
                                  f"{c.floor:g} m")
        dem = Dem(config, seed=int(self.rng.integers(2 ** 31)))
        dem.time = float(t)
        free = self.surface_dem
        if free is not None and len(free):  # the surface layer goes over too (lifted to rest)
            self._append(free.ids, free.mass, free.pos)
            free.remove(free.ids)
        slots = self.particles.slots(self._ids)
        tracking = (self.particles.attribute("tracking_id")[slots]
                    if "tracking_id" in self.particles.attribute_names else self._ids)
        radius = 0.5 * config.diameter_of_mass(self._mass)
        position = drop_heights(self._pos, radius, 0.0, -half, half)
        dem.place(position, self._mass, self.particles.grade[slots],
                  self.particles.hardness[slots], self.particles.f[slots],
                  np.asarray(tracking).astype(np.uint64), ids=self._ids)
        dem.credits[0] = self._credit_kg
        self.dem_storage = DemStorage(dem=dem, rng=self.rng).bind(self.particles, self.owner)
        self.dem_storage.sync()
        self.fallen_back_at = float(t)
        self._keep(np.zeros(self._ids.size, dtype=bool))
        warnings.warn(f"ROM stockpile continues as DEM from t = {t:g} s "
                      f"({len(slots)} particles handed over)", OutOfTrainingRange, stacklevel=3)

    # ------------------------------------------------------------ queries
    def held_ids(self) -> np.ndarray:
        """Held ids, nearest to the outlet first (the feeder's current order)."""
        if self.dem_storage is not None:
            return self.dem_storage.held_ids()
        bulk = self._ids[self._nearest_first(self._pos, self._ids.size)]
        if self.surface_dem is not None and len(self.surface_dem):
            return np.concatenate((bulk, self.surface_dem.ids))  # still on their way down
        return bulk

    def bulk_snapshot(self, t: float) -> dict:
        """The bulk particles (not the surface layer) at time ``t`` [s]: a copy of
        their ``id``, ``position`` [m] and ``mass`` [kg], the form
        ``surrogate.rom.dispersion.dispersion_fit`` takes."""
        return {"time": t, "id": self._ids.copy(), "position": self._pos.copy(),
                "mass": self._mass.copy()}

    def _forget(self, ids) -> None:
        self._keep(~np.isin(self._ids, ids))
        if self.surface_dem is not None:
            self.surface_dem.remove(ids)

    def predict(self, horizon: float, discharge_rate: float):
        """Feed for the next ``horizon`` s: ``(ids, mass_kg)``.

        The held particles are advected forward with the current field at a
        constant ``discharge_rate`` and no inflow (the funnel zone drains),
        without the random dispersion (the forecast follows the mean flow);
        the ones the outlet takes, then the nearest remaining ones, then the
        surface layer's particles still falling, are credited until
        rate * horizon (plus the current credit) is covered.
        """
        return self.predict_each((horizon,), discharge_rate)[0]

    def predict_each(self, horizons, discharge_rate: float) -> list:
        """``predict`` for each of ``horizons`` [s], all read from one forecast run
        to the longest (the order in which the particles reach the outlet), so a
        profile of the feed costs one forecast rather than one per horizon."""
        if self.dem_storage is not None:
            return self.dem_storage.predict_each(horizons, discharge_rate)
        rate = check_discharge_rate(discharge_rate)
        horizons = [float(check_finite_range("horizon", h, 0.0, unit="s")) for h in horizons]
        ids, masses = self._leaving_order(max(horizons, default=0.0), rate)
        return [budget_shares(ids, masses, self._credit_kg + rate * h) for h in horizons]

    def _leaving_order(self, horizon: float, rate: float):
        """``(ids, mass_kg)`` of the held particles in the order the forecast of
        ``horizon`` [s] at ``rate`` [kg/s] has them leave (``predict``)."""
        position, mass, index = self._pos.copy(), self._mass.copy(), np.arange(self._ids.size)
        # no column has drained before the first particle arrives
        credit, taken_all = self._credit_kg, []
        drained = None if self._drained is None else self._drained.copy()
        order = self._order
        substeps = max(1, int(np.ceil(horizon / self.max_step)))
        h = horizon / substeps
        if self._field is not None:
            flow = (self._field, self._faces)
        else:
            field = self.velocity_field(0.0, rate)
            flow = (field, None)
            if self.transport != "repack":
                faces = self._project(field, mass_field(self.model.grid, position, mass), rate)
                flow = (centred(*faces), faces)
        for _ in range(substeps):
            if index.size == 0:
                break
            order = self._move(flow, h, position, mass, dispersion=False, hint=order)
            credit += rate * h
            taken, credit = self._take(position, mass, credit, drained)
            if taken.size:
                taken_all.append(index[taken])
                keep = np.ones(index.size, dtype=bool)
                keep[taken] = False
                position, mass, index = position[keep], mass[keep], index[keep]
                order = _renumbered(order, keep)
        order = np.concatenate(taken_all + [index[self._nearest_first(position, index.size)]])
        ids, masses = self._ids[order], self._mass[order]
        free = self.surface_dem
        if free is not None and len(free):  # the surface layer comes last: it has yet to land
            ids, masses = np.concatenate((ids, free.ids)), np.concatenate((masses, free.mass))
        return ids, masses

    def fields(self) -> dict[str, np.ndarray]:
        """Fields on the model grid: ``mass`` [kg/cell], ``velocity`` [m/s] (ny, nx, 2)
        as last predicted (after a hand-over: the DEM's mass-weighted particle
        velocity, 0 where empty), ``grade`` and ``hardness`` (mass-weighted,
        NaN if empty)."""
        model = self.model
        grid = model.grid
        if self.dem_storage is not None:
            dem = self.dem_storage.dem
            ids, position, mass = dem.id, dem.pos, dem.mass
            velocity = np.stack([np.nan_to_num(mean_field(grid, position, mass, dem.vel[:, k]))
                                 for k in range(2)], axis=-1)
        else:
            ids, position, mass = self._ids, self._pos, self._mass
            free = self.surface_dem
            if free is not None and len(free):
                ids, position, mass = (np.concatenate((ids, free.ids)),
                                       np.concatenate((position, free.pos)),
                                       np.concatenate((mass, free.mass)))
            velocity = self._field if self._field is not None else np.zeros(grid.shape + (2,))
        slots = self.particles.slots(ids)
        return {"mass": mass_field(grid, position, mass), "velocity": velocity,
                "grade": mean_field(grid, position, mass, self.particles.grade[slots]),
                "hardness": mean_field(grid, position, mass, self.particles.hardness[slots])}
