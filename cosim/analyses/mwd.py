"""Hardness from measurement-while-drilling (MWD), identified from the crusher torque.

Source: paper section "Identification of hardness from measurement-while-
drilling" with the crusher torque model of section "Simulator",
eq. (crusher_torque):

    tau_cr(t) = sum_{n in N_Vcr(t)} m_n h_n k_cr . f_n

m_n [kg] particle mass, h_n [-] hardness, f_n its 16 size fractions and
k_cr the crushing coefficients: 1.0 for the oversize classes
(d_k >= d_cr = 0.25 m) and 0.1 for the undersize. The MWD signal recorded at
the source follows s = h**beta (the paper's ground truth beta = 0.4, with a
uniform location error of 12.5 m: s_n = h(x_n + R(-dx, dx))**0.4). With the
ansatz s = h**beta the hardness of a tracked particle is h_n = s_n**(1/beta),
so the expected torque given beta is

    tau(t; beta) = c sum_{n in N_Vcr(t)} m_n s_n**(1/beta) k_cr . f_n

and beta (and optionally the scale c [N m per kg], default 1) is chosen to
minimise the squared difference to the observed torque (scipy.optimize).
Once beta is known, the hardness of material about to enter the crusher is
predicted from its MWD signal alone: h = s**(1/beta).

The set N_Vcr(t) is taken from the macro-tracking events (``enter`` and
``pass``/``exit`` of the crusher zone), the MWD signal is a per-particle
value keyed by particle id, so the fit runs on any run's time series and
event store.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import optimize

from cosim import blockmodel, jsonio
from cosim.analyses.tracking import F_COLUMNS, occupancy_sum
from cosim.errors import ValidationError
from cosim.master import Component
from cosim.numerics import power
from cosim.sizes import DIAMETERS

CRUSHER_GAP = 0.25
"""Crusher gap width d_cr [m] (paper section "Simulator")."""


def crushing_coefficients(gap: float = CRUSHER_GAP, oversize: float = 1.0,
                          undersize: float = 0.1) -> np.ndarray:
    """k_cr per size class: ``oversize`` (1.0) for d_k >= gap [m], else ``undersize`` (0.1)."""
    return np.where(DIAMETERS >= gap * (1 - 1e-12), oversize, undersize)


def mwd_of(stays: pd.DataFrame, mwd: pd.Series) -> np.ndarray:
    """The MWD signal of every stay's particle; every particle must have one."""
    values = mwd.reindex(stays["particle_id"].to_numpy()).to_numpy(dtype=np.float64)
    if not np.all(np.isfinite(values) & (values > 0)):
        bad = stays["particle_id"].to_numpy()[~(np.isfinite(values) & (values > 0))]
        raise ValidationError("mwd", "a finite signal > 0 for every particle in the crusher zone",
                              f"{bad.size} particle(s) without one, e.g. id {int(bad[0])}")
    return values


def expected_torque(stays: pd.DataFrame, signal: np.ndarray, beta: float, times,
                    k_cr: np.ndarray | None = None, scale: float = 1.0) -> np.ndarray:
    """tau(t; beta) = scale * sum_{n in zone at t} m_n s_n**(1/beta) k_cr.f_n [N m]."""
    k_cr = crushing_coefficients() if k_cr is None else k_cr
    kf = stays[F_COLUMNS].to_numpy() @ k_cr
    weights = stays["mass"].to_numpy() * kf * power(signal, 1.0 / beta)
    return scale * occupancy_sum(stays["t_in"].to_numpy(), stays["t_out"].to_numpy(),
                                 weights, times)


@dataclass
class MwdFit:
    """Result of ``fit_mwd_exponent``.

    beta [-]: fitted exponent of s = h**beta; scale [-]: torque scale c;
    rmse [N m]: root-mean-square torque residual; samples: time samples used.
    """

    beta: float
    scale: float
    rmse: float
    samples: int


def fit_mwd_exponent(times, torque, stays: pd.DataFrame, mwd: pd.Series, *,
                     k_cr: np.ndarray | None = None, bounds=(0.05, 2.0),
                     fit_scale: bool = False) -> MwdFit:
    """Fit beta of the ansatz s = h**beta to an observed crusher torque.

    Parameters
    ----------
    times, torque : array_like
        Sample times [s] (ascending) and observed crusher torque [N m].
    stays : DataFrame
        ``tracking.residence_intervals`` of the crusher zone.
    mwd : Series
        MWD signal [-] by particle id (the extrinsic attribute ``mwd``).
    k_cr : array (16,), optional
        Crushing coefficients (default: ``crushing_coefficients()``).
    bounds : (float, float)
        Search interval for beta (default 0.05 .. 2).
    fit_scale : bool
        Also fit the torque scale c in closed form (linear least squares for
        each beta) when the torque is known only up to a constant.

    Samples where the zone is empty and the observed torque is zero carry no
    information about beta and are dropped.
    """
    times = np.asarray(times, dtype=np.float64)
    torque = np.asarray(torque, dtype=np.float64)
    if times.shape != torque.shape or times.ndim != 1:
        raise ValidationError("torque", "a 1-D array of the same length as times",
                              f"got {torque.shape} and {times.shape}")
    finite = np.isfinite(torque)
    times, torque = times[finite], torque[finite]
    signal = mwd_of(stays, mwd)
    occupied = occupancy_sum(stays["t_in"].to_numpy(), stays["t_out"].to_numpy(),
                             np.ones(len(stays)), times) > 0
    keep = occupied | (torque != 0)
    times, torque = times[keep], torque[keep]
    if times.size < 3:
        raise ValidationError("torque", "at least 3 samples while the crusher zone holds ore",
                              f"got {times.size}")

    def residual(beta: float) -> tuple[np.ndarray, float]:
        model = expected_torque(stays, signal, beta, times, k_cr)
        scale = float(model @ torque / (model @ model)) if fit_scale else 1.0
        return scale * model - torque, scale

    result = optimize.minimize_scalar(lambda b: float(np.sum(residual(b)[0] ** 2)),
                                      bounds=bounds, method="bounded",
                                      options={"xatol": 1e-6})
    res, scale = residual(float(result.x))
    return MwdFit(beta=float(result.x), scale=scale, rmse=float(np.sqrt(np.mean(res ** 2))),
                  samples=int(times.size))


def predicted_hardness(signal, beta: float) -> np.ndarray:
    """Hardness from the MWD signal: h = s**(1/beta) [-]."""
    if not (np.isfinite(beta) and beta > 0):
        raise ValidationError("beta", "finite and > 0", f"got {beta!r}")
    return power(signal, 1.0 / beta)


def zone_hardness(stays: pd.DataFrame, mwd: pd.Series, times, betas) -> pd.DataFrame:
    """Mass-weighted hardness in the zone over time: true, and predicted from MWD per beta.

    The prediction for a particle exists as soon as it is dumped at the
    hopper, before it enters the crusher zone (its MWD signal travels with
    it). Columns: ``time``, ``hardness_true``, ``hardness_beta_<beta>``.
    NaN where the zone holds nothing.
    """
    signal = mwd_of(stays, mwd)
    mass = stays["mass"].to_numpy()
    t_in, t_out = stays["t_in"].to_numpy(), stays["t_out"].to_numpy()
    columns = [stays["hardness"].to_numpy()] + [predicted_hardness(signal, b) for b in betas]
    sums = occupancy_sum(t_in, t_out, mass[:, None] * np.column_stack(columns), times)
    total = occupancy_sum(t_in, t_out, mass, times)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(total[:, None] > 0, sums / total[:, None], np.nan)
    frame = pd.DataFrame({"time": np.asarray(times, dtype=np.float64),
                          "hardness_true": means[:, 0]})
    for j, b in enumerate(betas):
        frame[f"hardness_beta_{b:g}"] = means[:, j + 1]
    return frame


def hardness_prediction_rmse(stays: pd.DataFrame, mwd: pd.Series, beta: float) -> float:
    """Mass-weighted RMS error [-] of the per-particle hardness predicted from MWD."""
    predicted = predicted_hardness(mwd_of(stays, mwd), beta)
    mass = stays["mass"].to_numpy()
    err = predicted - stays["hardness"].to_numpy()
    return float(np.sqrt(np.sum(mass * err ** 2) / np.sum(mass)))


class MwdSurvey(Component):
    """Records the MWD signal of every new particle as its extrinsic attribute ``mwd``.

    Paper section "Identification of hardness from measurement-while-
    drilling": s_n = h(x_n + R(-dx, dx))**beta, with x_n the particle's
    position of origin along the mining direction, h the source's hardness
    profile, beta the true exponent (0.4) and dx the half-width [m] of the
    uniform location error (12.5 m). Added to a master after the assets, it
    finds the particles that appeared during the step (ids above the last
    seen), assigns each to the source whose ore body contains its origin,
    writes ``mwd`` into the particle store and keeps a log (``table()``:
    source, local origin x [m], mwd, by particle id) that outlives the
    particles.

    Parameters
    ----------
    particles : ParticleStore
    sources : dict
        name -> source asset with ``origin`` (3,) [m], ``length``,
        ``face_width``, ``face_height`` [m] and ``hardness`` (callable of the
        local coordinate x [m]).
    beta : float
        True exponent of s = h**beta [-] (default 0.4).
    location_error : float
        Half-width dx [m] of the location error (default 12.5).
    rng : numpy.random.Generator
        Seeded generator of the location errors.
    """

    name = "mwd_survey"

    def __init__(self, particles, sources: dict, *, beta: float = 0.4,
                 location_error: float = 12.5, rng: np.random.Generator):
        super().__init__()
        if not (np.isfinite(beta) and beta > 0):
            raise ValidationError("beta", "finite and > 0", f"got {beta!r}")
        if not (np.isfinite(location_error) and location_error >= 0):
            raise ValidationError("location_error", "finite and >= 0 m",
                                  f"got {location_error!r}")
        self.particles = particles
        self.sources = dict(sources)
        self.beta = float(beta)
        self.location_error = float(location_error)
        self.rng = rng
        particles.add_attribute("mwd")
        self._next_id = 0
        self._log: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    def step(self, t: float, dt: float) -> None:
        store = self.particles
        new = np.flatnonzero(store.id >= self._next_id)
        if new.size == 0:
            return
        self._next_id = int(store.id[new].max()) + 1
        signal = np.full(new.size, np.nan)
        source_index = np.full(new.size, -1, dtype=np.int64)
        local_x = np.full(new.size, np.nan)
        for k, source in enumerate(self.sources.values()):
            local = store.origin[new] - np.asarray(source.origin, dtype=float)
            size = np.array([source.length, source.face_width, source.face_height])
            inside = np.all((local >= -1e-9) & (local <= size + 1e-9), axis=1)
            if inside.any():
                x = local[inside, 0]
                signal[inside] = blockmodel.mwd_signal(
                    source.hardness, x, beta=self.beta, location_error=self.location_error,
                    rng=self.rng)
                source_index[inside] = k
                local_x[inside] = x
        store.attribute("mwd")[new] = signal
        self._log.append((store.id[new].astype(np.int64), source_index, local_x, signal))

    def table(self) -> pd.DataFrame:
        """Particle id -> ``source`` (name), ``x`` (local origin [m]) and ``mwd`` [-]."""
        names = np.array(list(self.sources) + [""], dtype=object)
        if not self._log:
            return pd.DataFrame({"source": [], "x": [], "mwd": []},
                                index=pd.Index([], name="particle_id"))
        ids, index, x, signal = (np.concatenate(parts) for parts in zip(*self._log))
        return pd.DataFrame({"source": names[index], "x": x, "mwd": signal},
                            index=pd.Index(ids, name="particle_id"))


# ------------------------------------------------------------------ reproduce
DESCRIPTION = ("hardness from MWD: fit beta of s = h**beta from the crusher torque and the "
               "tracked origins, predict the hardness entering the crusher")
QUICK_UNTIL_S = 800.0
"""Simulated time of ``--quick`` [s]: the narrow-face quick run mines the whole profile
(h from 1 to 2 and back) by then."""
FULL_UNTIL_S = 2600.0
"""Simulated time of the full run [s]: 2,500 s of sampling after the first dump."""
BETA_TOLERANCE = 0.01
"""|beta_fit - 0.4| allowed with the paper's 12.5 m location error."""


def run_coefficients(config: dict) -> np.ndarray:
    """k_cr of a scenario's crusher FMU parameters (gap_width [m], k_oversize, k_undersize)."""
    params = config.get("assets", {}).get("crusher", {}).get("parameters", {})
    return crushing_coefficients(params.get("gap_width", CRUSHER_GAP),
                                 params.get("k_oversize", 1.0), params.get("k_undersize", 0.1))


def analyse(run, betas_shown=(0.3, 0.5)) -> tuple[dict, dict]:
    """Fit and prediction on a ``profile_run.ProfileRun``; (summary, plot data)."""
    from cosim.analyses.profile_run import MWD_BETA
    from cosim.analyses.tracking import residence_intervals

    times = run.times
    torque = run.timeseries["crusher_fmu.torque"].to_numpy()
    stays = residence_intervals(run.particles, "crusher_zone")
    signal = run.survey["mwd"]
    k_cr = run_coefficients(run.config)
    fit = fit_mwd_exponent(times, torque, stays, signal, k_cr=k_cr)
    frame = zone_hardness(stays, signal, times, [fit.beta, 0.42])
    occupied = frame["hardness_true"].notna()
    err = (frame.loc[occupied, f"hardness_beta_{fit.beta:g}"]
           - frame.loc[occupied, "hardness_true"])
    summary = {
        "beta_fit": fit.beta, "beta_true": MWD_BETA,
        "beta_rel_error": abs(fit.beta - MWD_BETA) / MWD_BETA,
        "torque_fit_rmse_nm": fit.rmse, "torque_samples": fit.samples,
        "hardness_prediction_rmse": float(np.sqrt(np.mean(err ** 2))),
        "particle_hardness_rmse": hardness_prediction_rmse(stays, signal, fit.beta),
        "crusher_zone_particles": int(len(stays)),
        "sampling_s": float(times[occupied.to_numpy()][-1] - times[occupied.to_numpy()][0]),
    }
    models = {b: expected_torque(stays, mwd_of(stays, signal), b, times, k_cr)
              for b in sorted({*betas_shown, round(fit.beta, 3)})}
    return summary, {"times": times, "torque": torque, "models": models, "zone": frame,
                     "fit": fit}


def plot(run, data: dict, summary: dict, out) -> list:
    """The paper's figures hardness_vs_MWD_tracking_error, crusher_observed_torque_models and
    crusher_torque_to_hardness, as PNG files in ``out``, titled with the run."""
    from cosim import plotstyle
    from cosim.analyses.profile_run import SCENARIO

    plt = plotstyle.pyplot()
    label = plotstyle.run_label(run.config, scenario=Path(SCENARIO).stem)
    out = Path(out)
    paths = []
    left = run.survey[run.survey["source"] == "left"]
    x = np.linspace(0.0, max(float(left["x"].max()), 1.0), 400)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(left["x"], left["mwd"], ".", ms=2, color="tab:green", alpha=0.5,
            label="MWD signal s_n (12.5 m location error)")
    ax.plot(x, run.profiles["left"](x), color="tab:blue", label="hardness h(x)")
    ax.plot(x, run.profiles["left"](x) ** summary["beta_true"], color="k", lw=0.8, ls="--",
            label="h(x)^0.4")
    ax.set_xlabel("origin x along the left ore body [m]")
    ax.set_ylabel("hardness, MWD signal [-]")
    ax.legend(fontsize=8)
    plotstyle.title(fig, "Hardness and MWD signal along the left ore body", label)
    fig.tight_layout()
    paths.append(plotstyle.save(fig, out / "hardness_vs_mwd_tracking_error.png"))

    times, torque = data["times"], data["torque"]
    # a window with four truck loads (two per source), where the profile is hard
    hard_t = times[np.nanargmax(data["zone"]["hardness_true"].to_numpy())]
    shown = (times >= hard_t - 60.0) & (times <= hard_t + 60.0)
    fig, ax = plt.subplots(figsize=(10, 4))
    ax.plot(times[shown], torque[shown], color="k", lw=1.5, label="observed torque")
    for b, model in data["models"].items():
        ax.plot(times[shown], model[shown], lw=0.9, label=f"ansatz s = h^beta, beta = {b:g}")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("crusher torque [N m]")
    # below the axes: inside, it covers the first truck load's torque
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=4)
    plotstyle.title(fig, "Crusher torque: observed and the ansatz s = h^beta", label)
    fig.tight_layout()
    paths.append(plotstyle.save(fig, out / "crusher_observed_torque_models.png"))

    zone = data["zone"]
    fig, ax = plt.subplots(figsize=(10, 4))
    ax.plot(zone["time"], zone["hardness_true"], color="k", lw=1.0, label="true hardness",
            zorder=3)
    beta = data["fit"].beta
    ax.plot(zone["time"], zone[f"hardness_beta_{beta:g}"], lw=0.8,
            label=f"predicted from MWD, beta = {beta:.3f} (fit)")
    ax.plot(zone["time"], zone["hardness_beta_0.42"], lw=0.8, label="predicted, beta = 0.42")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("hardness in the crusher zone [-]")
    ax.legend(fontsize=8)
    plotstyle.title(fig, "Hardness in the crusher zone: true and predicted from MWD", label)
    fig.tight_layout()
    paths.append(plotstyle.save(fig, out / "crusher_torque_to_hardness.png"))
    return paths


def reproduce(out_dir, *, quick: bool = False, progress: bool = True,
              location_error: float | None = None, seed: int | None = None):
    """Run the quadratic-profile scenario and identify beta; (summary, failed checks)."""

    from cosim.analyses.profile_run import (
        MWD_BETA,
        MWD_LOCATION_ERROR_M,
        output_folder,
        run_profile,
        scenario_config,
    )

    out = output_folder(out_dir)
    error = MWD_LOCATION_ERROR_M if location_error is None else float(location_error)
    until = QUICK_UNTIL_S if quick else FULL_UNTIL_S
    run = run_profile(out / "run", until=until, config=scenario_config(quick=quick),
                      location_error=error, seed=seed, progress=progress and "MWD run")
    summary, data = analyse(run)
    summary.update(quick=quick, simulated_s=until, location_error_m=error,
                   seed=run.config["simulation"]["seed"], wall_s=run.run_summary["wall_s"],
                   figures=[p.name for p in plot(run, data, summary, out)])
    tolerance = BETA_TOLERANCE if error > 0 else BETA_TOLERANCE / 2
    failed = []
    if not abs(summary["beta_fit"] - MWD_BETA) <= tolerance:
        failed.append(f"|beta_fit - {MWD_BETA}| = {abs(summary['beta_fit'] - MWD_BETA):.4f} "
                      f"> {tolerance}")
    summary["checks_failed"] = failed
    jsonio.write(out / "summary.json", summary, indent=2, sort_keys=True)
    return summary, failed
