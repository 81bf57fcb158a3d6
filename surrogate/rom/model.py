"""Reduced-order flow model of a stockpile: POD + ridge regression.

Source: Wallin and Servin (2021), "Data-driven model order reduction for
granular media", the method the paper's sections "Digital twin as a
distributed particle simulation" and "Integration test" use: from many
offline DEM runs, a low-dimensional model predicts the velocity field of the
pile from its mass distribution and the control signals.

Equations (our implementation):

- Mass field M (ny*nx cells, kg) reduced by proper orthogonal decomposition
  (PCA of the training snapshots): z = Phi_M^T (M - M_mean) / s_M, with
  Phi_M the first ``n_mass_modes`` left singular vectors and s_M the scale
  of each coefficient (singular value / sqrt(S)), so z is O(1).
- Velocity field V (ny*nx*2, m/s) reduced by uncentred POD:
  V ~= Phi_V a, ``n_velocity_modes`` modes.
- Features phi = [q_out, q_in, q_out z, q_in z] with the discharge rate
  q_out and inflow rate q_in [kg/s] divided by ``RATE_SCALE``: the flow is
  linear in the rates for each pile shape (a funnel flow field is close to
  proportional to the discharge rate) and vanishes when nothing enters or
  leaves (a pile at rest does not flow; an intercept would only fit the
  rattling and avalanche noise of the DEM samples).
- Ridge regression a = W phi, W = argmin |A - W Phi|^2 + lambda |W|^2,
  solved in closed form.

Parameters: ``n_mass_modes`` (default 12), ``n_velocity_modes`` (default
16), ``ridge`` lambda (default 1e-2, dimensionless: features are O(1)).

Fitted field (``target``, default "velocity", the above). ``target="flux"``
fits the cell's mass flux instead: F = M V [kg m/s per cell], the mass field
times the (mass-weighted) velocity field of the same sample, i.e. the DEM
cell's summed particle momentum over its particles' mass-weighted
displacement, reduced by the same uncentred POD and regressed on the same
features (the model's ``velocity_*`` arrays then hold F's modes, mean and
scales, in kg m/s). The velocity the model returns is the predicted flux over
the cell mass it is given: V = F / max(M, f0 M_full), M_full = rho_A dx dy the
mass of a full cell (``Container.areal_density``), f0 = ``flux_floor`` [-]
(default ``FLUX_FLOOR`` = 0.5; ``minetwin rom train --target flux`` chooses it
among ``FLUX_FLOORS`` by the same leave-one-run-out error). In the filled
cells (M >= f0 M_full) the velocity carries exactly the fitted flux; in a
cell with less mass (a surface cell, a cell the ROM has just emptied) the
floor keeps a flux fitted on DEM cells with a different fill from becoming
an unbounded speed (f0 = 1 passes the flux per full cell, F / M_full, i.e.
the volume flux the balanced transport's bulk faces carry, to the transport
directly). Why: the velocity fit weights every cell alike, so it spreads
its error over the thin surface cells and under-resolves the funnel core;
the flux is what the transport must carry through every row (the diagnosis
in surrogate/rom/README.md, "What limits the accuracy now").

Fitted fill (``fill_law="dem"``, flux fit only; default None: off). The DEM's
flowing cells are looser than its settled bulk (over the feeder's opening the
bottom row holds about 0.7 of a full cell while the feeder draws, 0.9 at rest),
but the ROM packs every bulk cell at rho_A, so F / M turns the DEM's flux into
too low a speed there. With the law the flux is divided by the cell's mass, but
no more than the DEM's fill of a cell carrying that flux:
V = F / max(min(M, phi(j) M_full), f0 M_full), j = |F| / M_full [m/s] the
predicted volume flux per full cell, and phi(j) [-] the DEM's mean fill of the
training samples' covered cells (those whose cell above holds at least
``COVER_FILL`` of a full cell; a surface cell is partly filled by the free
surface, not by dilation) in bins of j (edges ``FILL_LAW_BINS``), linear in j
between the bins' mean j, constant beyond them; fitted separately for the
feeder's cells (bottom row, centre over the opening) and for the others
(``fill_law_tables``; the arrays ``fill_law_*`` of the model file). Source of
the law: a binned regression of the training DEM's own fields (no physical
law is assumed; the dilatancy of sheared granular matter, Reynolds 1885,
"On the dilatancy of media composed of rigid particles in contact", Phil.
Mag. 20, 469-481, is why a flowing cell is looser).

Registered fit (``registration="height"``, velocity fit only; default None:
off). The velocity samples are registered on height-following levels before
the POD (``surrogate.rom.registration``: each column's velocity at heights in
units of the column's own height, eta = (y - y_min) / H(x), ``grid.ny``
levels), the regression predicts the registered field's coefficients, and
``predict`` maps the prediction back onto the grid of the mass field it is
given, whose column heights are its column masses over
``registration_density`` [kg/m^2] (the training DEM's settled density,
``surrogate.rom.packing.settled_density``, as ``minetwin rom train`` sets it;
default the container's areal density) unless ``predict(areal_density=...)``
names the density that mass field is packed at (``RomStorage`` passes its own).
Why: the fixed grid's POD does not carry the funnel's core where each pile puts
it (surrogate/rom/README.md, "What the fit can reach").

The model file (``save``/``load``) is one ``.npz`` holding the arrays and a
JSON header with the format version, the grid, the options and the training
ranges of every input. ``predict`` warns (``OutOfTrainingRange``) naming the
input and its range when an input lies outside what the model was trained on:
discharge rate, inflow rate, held mass, and the mass distribution (relative
residual of its POD projection above the training maximum; ``minetwin rom
train`` widens that maximum to what states of a run left out of the fit show,
``surrogate.rom.evaluate.leave_one_run_out_residual``).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from cosim.errors import ValidationError
from surrogate.rom import registration
from surrogate.rom.container import Container
from surrogate.rom.grid import Grid

FORMAT_VERSION = 1
"""Version of the model file layout."""

RATE_SCALE = 1000.0
"""Rates are divided by this [kg/s] before entering the regression."""

RANGE_MARGIN = 0.05
"""Relative slack on the training ranges before ``predict`` warns."""

TARGETS = ("velocity", "flux")
"""Accepted values of ``RomModel(target=...)``: the field the regression fits."""

FLUX_FLOOR = 0.5
"""Default least fill [-] of a full cell's mass that ``target="flux"`` divides by."""

FLUX_FLOORS = (0.25, 0.5, 1.0)
"""Fills tried for ``flux_floor`` by ``minetwin rom train --target flux``."""

FILL_LAWS = (None, "dem")
"""Accepted values of ``RomModel(fill_law=...)`` (module docstring, "Fitted fill")."""

REGISTRATIONS = (None, "height")
"""Accepted values of ``RomModel(registration=...)`` (module docstring, "Registered fit")."""

FILL_LAW_BINS = (0.0, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5)
"""Lower edges [m/s] of the bins of j = |F| / M_full the fill law is fitted in
(the last bin is open above)."""

COVER_FILL = 0.5
"""Least fill [-] of the cell above that makes a cell covered (fill law)."""


def feeder_cells(grid: Grid, container: Container) -> np.ndarray:
    """Boolean (ny, nx): the bottom-row cells whose centre lies over the feeder's
    opening (``outlet_x +- outlet_width / 2``)."""
    x, _ = grid.centres()
    cells = np.zeros((grid.ny, grid.nx), dtype=bool)
    cells[0] = np.abs(x - container.outlet_x) <= 0.5 * container.outlet_width
    return cells


def covered_cells(mass, full_cell_mass: float) -> np.ndarray:
    """Boolean, the shape of ``mass`` (..., ny, nx) [kg]: the cell above holds at least
    ``COVER_FILL`` full cells (the top row is never covered)."""
    mass = np.asarray(mass, dtype=np.float64)
    covered = np.zeros(mass.shape, dtype=bool)
    covered[..., :-1, :] = mass[..., 1:, :] >= COVER_FILL * full_cell_mass
    return covered


def fill_law_tables(mass, flux, feeder, full_cell_mass: float) -> dict:
    """The fill law's arrays from samples: ``mass`` (S, ny, nx) [kg], ``flux``
    (S, ny, nx, 2) [kg m/s], ``feeder`` (ny, nx) the feeder's cells: for the
    feeder's covered cells (``fill_law_feeder_j``, ``fill_law_feeder_fill``) and
    the other covered cells (``fill_law_bulk_*``), each bin of j = |F| / M_full
    [m/s] (edges ``FILL_LAW_BINS``) holding samples: its mean j and mean fill
    M / M_full [-] (module docstring). Without covered feeder cells (a point
    outlet) the feeder's law is the bulk's."""
    mass = np.asarray(mass, dtype=np.float64)
    flux = np.asarray(flux, dtype=np.float64).reshape(*mass.shape, 2)
    fill = mass / full_cell_mass
    j = np.sqrt(flux[..., 0] ** 2 + flux[..., 1] ** 2) / full_cell_mass
    covered = covered_cells(mass, full_cell_mass)
    out = {}
    for name, cells in (("bulk", ~feeder), ("feeder", feeder)):
        use = covered & cells[None]
        jj, ff = j[use], fill[use]
        if name == "feeder" and jj.size == 0:  # a point outlet: the bulk's law
            out["fill_law_feeder_j"] = out["fill_law_bulk_j"].copy()
            out["fill_law_feeder_fill"] = out["fill_law_bulk_fill"].copy()
            continue
        if jj.size == 0:
            raise ValidationError("fill_law", "covered cells in the samples", "none")
        bins = np.searchsorted(np.asarray(FILL_LAW_BINS), jj, side="right") - 1
        count = np.bincount(bins, minlength=len(FILL_LAW_BINS))
        kept = count > 0
        out[f"fill_law_{name}_j"] = (np.bincount(bins, jj, len(FILL_LAW_BINS))[kept]
                                     / count[kept])
        out[f"fill_law_{name}_fill"] = (np.bincount(bins, ff, len(FILL_LAW_BINS))[kept]
                                        / count[kept])
    return out


def fill_law(arrays: dict, j, feeder) -> np.ndarray:
    """phi(j) [-] per cell from the tables ``arrays`` (``fill_law_tables``), ``j``
    (ny, nx) [m/s], ``feeder`` (ny, nx) the feeder's cells."""
    j = np.asarray(j, dtype=np.float64)
    bulk = np.interp(j, arrays["fill_law_bulk_j"], arrays["fill_law_bulk_fill"])
    at_feeder = np.interp(j, arrays["fill_law_feeder_j"], arrays["fill_law_feeder_fill"])
    return np.where(feeder, at_feeder, bulk)


class OutOfTrainingRange(UserWarning):
    """An input to the ROM lies outside the range it was trained on."""


def pod_basis(snapshots: np.ndarray, centred: bool = True) -> tuple:
    """``(mean, singular values, right singular vectors, count)`` of ``snapshots``
    (S, cells): the SVD every POD truncation of them is cut from."""
    snapshots = np.asarray(snapshots, dtype=np.float64).reshape(len(snapshots), -1)
    mean = snapshots.mean(axis=0) if centred else np.zeros(snapshots.shape[1])
    _, singular, vt = np.linalg.svd(snapshots - mean, full_matrices=False)
    return mean, singular, vt, snapshots.shape[0]


def _pod(basis: tuple, modes: int):
    """Mean, orthonormal modes (cells, k) and coefficient scales of the first
    ``modes`` of a ``pod_basis``."""
    mean, singular, vt, count = basis
    modes = min(modes, vt.shape[0])
    scale = singular[:modes] / np.sqrt(count)
    scale = np.where(scale > 0, scale, 1.0)
    return mean, vt[:modes].T.copy(), scale


def flux_samples(mass, velocity) -> np.ndarray:
    """Mass flux M V [kg m/s per cell] of samples: ``mass`` (S, ny, nx) or (S, cells)
    [kg] times ``velocity`` (S, ny, nx, 2) or (S, 2 cells) [m/s], flattened (S, 2 cells)."""
    mass = np.asarray(mass, dtype=np.float64).reshape(len(mass), -1)
    velocity = np.asarray(velocity, dtype=np.float64).reshape(len(velocity), -1, 2)
    return (velocity * mass[:, :, None]).reshape(len(mass), -1)


def pod_residual(basis: tuple, modes: int, mass) -> np.ndarray:
    """Relative norm of the part of each mass field of ``mass`` (S, cells) that the
    first ``modes`` of a (centred) ``pod_basis`` do not span."""
    mean, phi, _ = _pod(basis, modes)
    centred = np.asarray(mass, dtype=np.float64).reshape(len(mass), -1) - mean
    norm = np.linalg.norm(centred + mean, axis=1)
    rest = centred - (centred @ phi) @ phi.T
    return np.linalg.norm(rest, axis=1) / np.where(norm > 0, norm, 1.0)


class RomModel:
    """POD + ridge regression from (mass field, rates) to velocity field.

    Parameters
    ----------
    grid : Grid
        The Eulerian grid the fields live on.
    n_mass_modes : int
        POD modes kept of the mass field (default 12).
    n_velocity_modes : int
        POD modes kept of the velocity field (default 16).
    ridge : float
        Ridge penalty lambda [-] (default 1e-2).
    container : Container, optional
        The stockpile geometry the training data came from (saved with the
        model; the storage asset needs it).
    dem_config : dict, optional
        The training DEM's configuration (``DemConfig.to_dict()``; saved
        with the model): the storage's surface-layer DEM uses its contact
        law, particle density and inlet.

    target : {"velocity", "flux"}
        The fitted field (default "velocity"; module docstring).
    flux_floor : float
        With ``target="flux"``: least fill [-] of a full cell the flux is divided
        by (default ``FLUX_FLOOR`` = 0.5).
    fill_law : {None, "dem"}
        With ``target="flux"``: divide the flux by no more than the DEM's fitted
        fill of a cell carrying it (default None: off; module docstring,
        "Fitted fill").
    registration : {None, "height"}
        With ``target="velocity"``: fit the velocity on height-following levels
        (default None: off; module docstring, "Registered fit").
    registration_density : float, optional
        Areal density [kg/m^2] the column heights of the registration are
        measured at (default: the container's ``areal_density``).

    ``dispersivity`` [m] (default 0: none) is the bulk's dispersion about the
    mean flow measured on the training DEM (``surrogate.rom.dispersion``);
    ``rest_fraction`` [-] (default 0: off) the share of the feeder's mean outlet
    speed below which a cell of the predicted field rests, fitted on the
    training DEM (``surrogate.rom.rest``; ``RomStorage``'s default).
    ``storage_settings`` (default {}: the storage's own defaults) are the
    ``RomStorage`` options ``packing``, ``packing_density`` [kg/m^2] and
    ``landing_spread`` [m] a model chosen by tracking (``minetwin rom train
    --validation``) was chosen under: the storage's defaults for it.
    ``minetwin rom train`` sets them and the file keeps them, as it keeps the
    ``provenance`` (``surrogate.rom.provenance``: data, design, seeds, code
    version, the command that regenerates the file).
    """

    def __init__(self, grid: Grid, n_mass_modes: int = 12, n_velocity_modes: int = 16,
                 ridge: float = 1e-2, container: Container | None = None,
                 dem_config: dict | None = None, target: str = "velocity",
                 flux_floor: float = FLUX_FLOOR, fill_law: str | None = None,
                 registration: str | None = None, registration_density: float | None = None):
        if target not in TARGETS:
            raise ValidationError("target", f"one of {TARGETS}", f"got {target!r}")
        if target == "flux" and container is None:
            raise ValidationError("container", "a container (its areal density) for "
                                  "target 'flux'", "got None")
        if fill_law not in FILL_LAWS:
            raise ValidationError("fill_law", f"one of {FILL_LAWS}", f"got {fill_law!r}")
        if fill_law is not None and target != "flux":
            raise ValidationError("fill_law", "None unless target is 'flux'",
                                  f"got {fill_law!r} with target {target!r}")
        if registration not in REGISTRATIONS:
            raise ValidationError("registration", f"one of {REGISTRATIONS}",
                                  f"got {registration!r}")
        if registration is not None and target != "velocity":
            raise ValidationError("registration", "None unless target is 'velocity'",
                                  f"got {registration!r} with target {target!r}")
        if registration is not None and registration_density is None:
            if container is None:
                raise ValidationError("registration_density", "a density [kg/m^2] or a "
                                      "container to take it from", "got neither")
            registration_density = container.areal_density
        if registration_density is not None and not registration_density > 0:
            raise ValidationError("registration_density", "> 0 kg/m^2",
                                  f"got {registration_density!r}")
        if not 0 < flux_floor:
            raise ValidationError("flux_floor", "> 0", f"got {flux_floor!r}")
        if n_mass_modes < 1 or n_velocity_modes < 1:
            raise ValidationError("modes", ">= 1", f"got {n_mass_modes}, {n_velocity_modes}")
        if not ridge >= 0:
            raise ValidationError("ridge", ">= 0", f"got {ridge!r}")
        self.grid = grid
        self.n_mass_modes = int(n_mass_modes)
        self.n_velocity_modes = int(n_velocity_modes)
        self.ridge = float(ridge)
        self.container = container
        self.dem_config = dem_config
        self.target = target
        self.flux_floor = float(flux_floor)
        self.fill_law = fill_law
        self.registration = registration
        self.registration_density = (None if registration_density is None
                                     else float(registration_density))
        self.dispersivity = 0.0
        self.rest_fraction = 0.0
        self.storage_settings: dict = {}
        self.arrays: dict[str, np.ndarray] = {}
        self.ranges: dict[str, list[float]] = {}
        self.n_samples = 0
        self.validation: dict = {}
        self.provenance: dict = {}

    # ------------------------------------------------------------ training
    def fit(self, mass, discharge_rate, inflow_rate, velocity, bases=None) -> "RomModel":
        """Train on S samples.

        Parameters
        ----------
        mass : array (S, ny, nx)
            Mass per cell [kg].
        discharge_rate, inflow_rate : array (S,)
            Control signals [kg/s].
        velocity : array (S, ny, nx, 2)
            Velocity per cell [m/s].
        bases : (mass basis, velocity basis), optional
            ``pod_basis`` of these very mass (centred) and velocity (uncentred)
            samples, to fit models of several mode counts without redoing the
            SVDs (model selection); the result is the same as without. With
            ``target="flux"`` the velocity basis is that of the flux
            (``flux_samples``), with a registration that of the registered
            velocity (``registered``).
        """
        mass = np.asarray(mass, dtype=np.float64).reshape(len(mass), -1)
        flux_input = None
        if self.registration is not None:
            velocity = self.registered(mass, velocity)
        velocity = np.asarray(velocity, dtype=np.float64).reshape(len(velocity), -1)
        if self.target == "flux" and velocity.shape[1] == 2 * mass.shape[1]:
            velocity = flux_input = flux_samples(mass, velocity)
        q_out = np.asarray(discharge_rate, dtype=np.float64)
        q_in = np.asarray(inflow_rate, dtype=np.float64)
        samples = mass.shape[0]
        if mass.shape[1] != self.grid.n_cells or velocity.shape[1] != 2 * self.grid.n_cells:
            raise ValidationError("mass/velocity", f"fields on the {self.grid.shape} grid",
                                  f"got {mass.shape[1]} and {velocity.shape[1]} values")
        if not (velocity.shape[0] == q_out.size == q_in.size == samples) or samples < 2:
            raise ValidationError("samples", "equal counts >= 2 of mass, rates and velocity",
                                  f"got {samples}, {q_out.size}, {q_in.size}, {velocity.shape[0]}")
        if bases is None:
            bases = (pod_basis(mass), pod_basis(velocity, centred=False))
        m_mean, m_modes, m_scale = _pod(bases[0], self.n_mass_modes)
        v_mean, v_modes, v_scale = _pod(bases[1], self.n_velocity_modes)
        self.arrays = {"mass_mean": m_mean, "mass_modes": m_modes, "mass_scale": m_scale,
                       "velocity_mean": v_mean, "velocity_modes": v_modes,
                       "velocity_scale": v_scale}
        z = (mass - m_mean) @ m_modes / m_scale
        features = self._features(z, q_out, q_in)
        target = (velocity - v_mean) @ v_modes / v_scale
        penalty = self.ridge * np.eye(features.shape[1])
        weights = np.linalg.solve(features.T @ features + penalty, features.T @ target)
        self.arrays["weights"] = weights
        if self.fill_law == "dem":
            if flux_input is None:
                raise ValidationError("fill_law", "velocity samples (S, ny, nx, 2) to fit "
                                      "the fill law on", "got flux samples")
            self.arrays.update(fill_law_tables(
                mass.reshape(samples, self.grid.ny, self.grid.nx),
                flux_input.reshape(samples, self.grid.ny, self.grid.nx, 2),
                feeder_cells(self.grid, self.container), self.full_cell_mass))
        residual = self._residual(mass, z)
        totals = mass.sum(axis=1)
        self.ranges = {
            "discharge_rate": [float(q_out.min()), float(q_out.max())],
            "inflow_rate": [float(q_in.min()), float(q_in.max())],
            "held_mass": [float(totals.min()), float(totals.max())],
            "mass_distribution_residual": [0.0, float(residual.max())],
        }
        self.n_samples = samples
        return self

    def registered(self, mass, velocity) -> np.ndarray:
        """Velocity samples (S, ny, nx, 2) [m/s] of the mass fields ``mass`` (S, ny,
        nx) [kg] on the registration's levels, flattened (S, 2 ny nx): what the
        velocity POD of a registered fit decomposes."""
        mass = np.asarray(mass, dtype=np.float64).reshape(len(mass), self.grid.ny,
                                                          self.grid.nx)
        velocity = np.asarray(velocity, dtype=np.float64).reshape(
            len(velocity), self.grid.ny, self.grid.nx, 2)
        return registration.register(velocity, mass, self.grid,
                                     self.registration_density).reshape(len(mass), -1)

    @staticmethod
    def _features(z, q_out, q_in) -> np.ndarray:
        z = np.atleast_2d(z)
        q_out = np.atleast_1d(q_out)[:, None] / RATE_SCALE
        q_in = np.atleast_1d(q_in)[:, None] / RATE_SCALE
        return np.hstack((q_out, q_in, q_out * z, q_in * z))

    def _residual(self, mass, z) -> np.ndarray:
        """Relative norm of the part of each mass field the POD modes do not span."""
        a = self.arrays
        centred = mass - a["mass_mean"]
        rebuilt = (z * a["mass_scale"]) @ a["mass_modes"].T
        norm = np.linalg.norm(mass, axis=1)
        return np.linalg.norm(centred - rebuilt, axis=1) / np.where(norm > 0, norm, 1.0)

    # ----------------------------------------------------------- inference
    @property
    def trained(self) -> bool:
        return "weights" in self.arrays

    def mass_residual(self, mass) -> float:
        """Relative part of one mass field ``(ny, nx)`` the POD modes do not span."""
        a = self.arrays
        flat = np.asarray(mass, dtype=np.float64).reshape(1, -1)
        z = (flat - a["mass_mean"]) @ a["mass_modes"] / a["mass_scale"]
        return float(self._residual(flat, z)[0])

    def check_ranges(self, mass, discharge_rate: float, inflow_rate: float,
                     residual: float | None = None, warn: bool = True) -> dict[str, str]:
        """Messages ``{input name: text}`` for every input outside the training
        range; each is also warned (``OutOfTrainingRange``) unless ``warn`` is false."""
        values = {"discharge_rate": discharge_rate, "inflow_rate": inflow_rate,
                  "held_mass": float(np.sum(mass))}
        if residual is not None:
            values["mass_distribution_residual"] = residual
        units = {"discharge_rate": "kg/s", "inflow_rate": "kg/s", "held_mass": "kg",
                 "mass_distribution_residual": ""}
        messages = {}
        for name, value in values.items():
            low, high = self.ranges[name]
            slack = RANGE_MARGIN * max(abs(high), abs(low), 1e-12)
            if name == "mass_distribution_residual":
                slack = max(slack, 0.05)
            if value < low - slack or value > high + slack:
                unit = f" {units[name]}" if units[name] else ""
                message = (f"ROM input {name} = {value:.4g}{unit} is outside the "
                           f"training range [{low:.4g}, {high:.4g}]{unit}; "
                           "prediction is an extrapolation (consider the DEM fidelity)")
                if warn:
                    warnings.warn(message, OutOfTrainingRange, stacklevel=3)
                messages[name] = message
        return messages

    @property
    def full_cell_mass(self) -> float:
        """Mass [kg] of a full cell, rho_A dx dy (``nan`` without a container)."""
        if self.container is None:
            return float("nan")
        return self.container.full_cell_mass(self.grid)

    def predict(self, mass, discharge_rate: float, inflow_rate: float = 0.0,
                check: bool = True, areal_density: float | None = None) -> np.ndarray:
        """Velocity field [m/s], ``(ny, nx, 2)``, for one mass field ``(ny, nx)`` [kg]
        and rates [kg/s]; with ``target="flux"`` the predicted flux over
        max(mass, ``flux_floor`` full cells); with a registration mapped back by the
        column heights of ``mass`` packed at ``areal_density`` [kg/m^2] (default
        ``registration_density``) (module docstring)."""
        field, flat, z = self._fitted_field(mass, discharge_rate, inflow_rate, areal_density)
        if check:  # here, so that the warning names the caller of predict
            self.check_ranges(flat, discharge_rate, inflow_rate,
                              float(self._residual(flat, z)[0]))
        if self.target == "velocity":
            return field
        return field / self._divisor(mass, field)[..., None]

    def predict_flux(self, mass, discharge_rate: float, inflow_rate: float = 0.0,
                     check: bool = True) -> np.ndarray:
        """Mass flux [kg m/s per cell], ``(ny, nx, 2)``: the fitted flux
        (``target="flux"``) or the mass field times the predicted velocity (mapped
        back at ``registration_density`` with a registration)."""
        field, flat, z = self._fitted_field(mass, discharge_rate, inflow_rate)
        if check:
            self.check_ranges(flat, discharge_rate, inflow_rate,
                              float(self._residual(flat, z)[0]))
        if self.target == "flux":
            return field
        return field * np.asarray(mass, dtype=np.float64).reshape(self.grid.ny, self.grid.nx, 1)

    def _divisor(self, mass, flux=None) -> np.ndarray:
        """max(M, flux_floor M_full) [kg] per cell (ny, nx); with the fill law,
        max(min(M, phi(|F| / M_full) M_full), flux_floor M_full) for the fitted
        flux ``flux`` (ny, nx, 2) [kg m/s] (module docstring)."""
        mass = np.asarray(mass, dtype=np.float64).reshape(self.grid.ny, self.grid.nx)
        full = self.full_cell_mass
        if self.fill_law == "dem":
            flux = np.asarray(flux, dtype=np.float64).reshape(self.grid.ny, self.grid.nx, 2)
            j = np.sqrt(flux[..., 0] ** 2 + flux[..., 1] ** 2) / full
            phi = fill_law(self.arrays, j, feeder_cells(self.grid, self.container))
            mass = np.minimum(mass, phi * full)
        return np.maximum(mass, self.flux_floor * full)

    def fitted_fill(self, mass, discharge_rate: float, inflow_rate: float = 0.0) -> np.ndarray:
        """The fill [-] (ny, nx) the flux is divided by, divisor / M_full: the fill
        law's min(M / M_full, phi(j)) floored at ``flux_floor`` (without the law:
        max(M / M_full, flux_floor)); ``target="flux"`` only."""
        if self.target != "flux":
            raise ValidationError("target", "'flux' for fitted_fill", f"got {self.target!r}")
        field, _, _ = self._fitted_field(mass, discharge_rate, inflow_rate)
        return self._divisor(mass, field) / self.full_cell_mass

    def _fitted_field(self, mass, discharge_rate: float, inflow_rate: float,
                      areal_density: float | None = None) -> tuple:
        """``(field, flat mass, z)``: the regressed field (``target``'s unit),
        ``(ny, nx, 2)``, on the grid (a registered one mapped back by the column
        heights of ``mass`` at ``areal_density``, default ``registration_density``),
        the mass field (1, cells) and its POD coefficients."""
        if not self.trained:
            raise ValidationError("model", "a trained model (call fit or load first)")
        a = self.arrays
        flat = np.asarray(mass, dtype=np.float64).reshape(1, -1)
        if flat.shape[1] != self.grid.n_cells:
            raise ValidationError("mass", f"a field on the {self.grid.shape} grid",
                                  f"got {flat.shape[1]} values")
        z = (flat - a["mass_mean"]) @ a["mass_modes"] / a["mass_scale"]
        coefficients = self._features(z, discharge_rate, inflow_rate) @ a["weights"]
        velocity = a["velocity_mean"] + (coefficients * a["velocity_scale"]) @ a["velocity_modes"].T
        field = velocity.reshape(1, self.grid.ny, self.grid.nx, 2)
        if self.registration is not None:
            field = registration.unregister(
                field, flat.reshape(1, self.grid.ny, self.grid.nx), self.grid,
                self.registration_density if areal_density is None else areal_density)
        return field[0], flat, z

    # ---------------------------------------------------------- persistence
    def header(self) -> dict:
        """The file's JSON header; ``target`` and ``flux_floor`` are written for a flux
        fit only (a file without them is a velocity fit, as every file before them),
        ``fill_law``, ``rest_fraction``, ``registration`` (with
        ``registration_density``) and ``storage_settings`` only when set (a file
        without ``rest_fraction``
        has the resting bulk off, as every file before it)."""
        header = self._header()
        if self.rest_fraction > 0.0:
            header.update(rest_fraction=self.rest_fraction)
        if self.target != "velocity":
            header.update(target=self.target, flux_floor=self.flux_floor)
        if self.fill_law is not None:
            header.update(fill_law=self.fill_law)
        if self.registration is not None:
            header.update(registration=self.registration,
                          registration_density=self.registration_density)
        if self.storage_settings:
            header.update(storage_settings=self.storage_settings)
        return header

    def _header(self) -> dict:
        return {"format": "minetwin-rom", "version": FORMAT_VERSION,
                "grid": self.grid.to_dict(), "n_mass_modes": self.n_mass_modes,
                "n_velocity_modes": self.n_velocity_modes, "ridge": self.ridge,
                "rate_scale": RATE_SCALE, "ranges": self.ranges, "n_samples": self.n_samples,
                "container": None if self.container is None else self.container.to_dict(),
                "validation": self.validation, "dem_config": self.dem_config,
                "dispersivity": self.dispersivity, "provenance": self.provenance}

    def save(self, path) -> Path:
        """Write the model as one ``.npz`` file (arrays + JSON header)."""
        if not self.trained:
            raise ValidationError("model", "a trained model (call fit first)")
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as handle:
            np.savez_compressed(handle, header=np.array(json.dumps(self.header())), **self.arrays)
        return path

    @classmethod
    def load(cls, path) -> "RomModel":
        """Read a model written by ``save``; a wrong file or version is a ValidationError."""
        path = Path(path)
        if not path.is_file():
            raise ValidationError("model", "an existing model file", f"no file {path}")
        try:
            with np.load(path, allow_pickle=False) as data:
                header = json.loads(str(data["header"]))
                arrays = {name: data[name].copy() for name in data.files if name != "header"}
        except (OSError, ValueError, KeyError) as exc:
            raise ValidationError("model", "a MineTwin ROM file (.npz)", f"{path}: {exc}") from None
        if header.get("format") != "minetwin-rom" or header.get("version") != FORMAT_VERSION:
            raise ValidationError("model", f"a minetwin-rom file of version {FORMAT_VERSION}",
                                  f"got {header.get('format')!r} version {header.get('version')!r}")
        if header.get("rate_scale") != RATE_SCALE:
            raise ValidationError("model", f"rate_scale {RATE_SCALE}",
                                  f"got {header.get('rate_scale')!r}")
        model = cls(Grid.from_dict(header["grid"]), header["n_mass_modes"],
                    header["n_velocity_modes"], header["ridge"],
                    None if header.get("container") is None
                    else Container.from_dict(header["container"]),
                    header.get("dem_config"), header.get("target", "velocity"),
                    float(header.get("flux_floor", FLUX_FLOOR)), header.get("fill_law"),
                    header.get("registration"), header.get("registration_density"))
        model.arrays = arrays
        model.ranges = {k: list(v) for k, v in header["ranges"].items()}
        model.n_samples = int(header["n_samples"])
        model.validation = header.get("validation", {})
        model.dispersivity = float(header.get("dispersivity", 0.0))
        model.rest_fraction = float(header.get("rest_fraction", 0.0))
        model.storage_settings = dict(header.get("storage_settings", {}))
        model.provenance = header.get("provenance", {})
        return model
