"""Scenarios: a declared plant in a TOML file; load, validate, build, run, write.

Source: paper section "Digital twin as a distributed particle simulation"
(each asset a = an operator on its particles; assets exchange particles and
signals) and section "Simulator" (the paper's mine is one scenario:
``examples/step_response.toml``). A scenario lists its assets by kind, each
with its parameters, and the flows and signals between them::

    [simulation]                      # until_s, step_s, record_every_s, seed, ...
    [assets.left]                     # an asset: its name, its kind, its parameters
    kind = "source"
    grade = 0.2
    ...
    [[flows]]                         # particles: outlet -> inlet
    from = "crusher.product"
    to = "belt.feed"
    fraction = 1.0                    # several flows out of one outlet split by mass
    [[signals]]                       # signals: output -> input, every step
    from = "stockpile.inlet_open"
    to = "belt.running"

Kinds come from the ``minetwin.assets`` entry points (``cosim.kinds``; the
built-in ones: source, truck_fleet, crusher, belt, screen, stockpile, mill);
each kind's ``Parameters`` model documents its keys, with the unit in the key
name (``_m``, ``_s``, ``_kg``, ``_kg_s``, ``_m_s``, ``_rad_s``). Assets are
stepped in the order they are listed (list them upstream first: material
handed on is then processed downstream in the same step; in a closed circuit
the return leg arrives one step later).

``[simulation]`` (defaults in brackets): until_s [1200], step_s [0.5],
record_every_s [= step_s], seed [1], sensor_window_s [30],
event_store_timeout_s [30]: how long a write waits for another process that
holds the event store's lock; coupling_tolerance [none] and coupling_signals
[[]]: the relative coupling error the declared signals' window means may carry,
for which `minetwin coupling-step` finds the largest step by step doubling;
communication_step ["fixed"]: "adaptive" adapts the step during the run within
[step_min_s [0.125], step_max_s [2]] s, each step_s times a power of two, to keep
the declared signals within coupling_tolerance (``cosim.master.AdaptiveStep``;
record_every_s then a whole multiple of step_max_s). The communication step
0.5 s resolves the fastest material dynamics of the paper's plant: a particle stays about 1 s in
the crusher zone (785 kg at 1 t/s) and the trucks dump every 27.5 s; the
FMUs' physics (crusher torque, mill speed with a 5 s time constant, mill
breakage with an exponential integrator) is smooth over it.

Validation is one pass that reports every error it finds (``ValidationErrors``),
each naming the dotted key (``assets.left.grade``), the allowed range and the
unit. It runs when a scenario is loaded and built, never per step.
"""

from __future__ import annotations

import copy
import time as wallclock
from dataclasses import dataclass, field
from pathlib import Path

from typing import Annotated

import numpy as np
from pydantic import BeforeValidator, Field, model_validator
from pydantic_core import PydanticCustomError

from cosim import jsonio
from cosim.errors import ValidationError, raise_all
from cosim.params import Parameters, Text, check, choice, number, refuse

WALL_CLOCK_FIELDS = ("wall_s", "realtime_factor")
"""Summary fields that depend on the machine, not on the scenario and seed."""


# ------------------------------------------------------------------ validation
class SimulationParameters(Parameters):
    until_s: number(0.0, 1e7, unit="s") = 1200.0
    step_s: number(1e-3, 5.0, unit="s") = 0.5
    record_every_s: number(1e-3, 3600.0, unit="s") | None = None
    """[s]; default: every step."""
    seed: number(0, 2**63 - 1, integer=True) = 1
    sensor_window_s: number(0.0, 3600.0, unit="s") = 30.0
    event_store_timeout_s: number(0.0, 3600.0, unit="s") = 30.0
    coupling_tolerance: number(0.0, 1.0, low_open=True) | None = None
    """Largest relative coupling error of the declared signals (``minetwin
    coupling-step``, ``cosim.analyses.coupling_step``) [-]; default: none declared."""
    coupling_signals: list[Text] = []
    """The signals (``component.output``) the coupling tolerance applies to."""
    communication_step: choice("fixed", "adaptive") = "fixed"
    """"fixed": every step is step_s; "adaptive": the master adapts the step during the
    run to keep the declared signals' coupling error within coupling_tolerance
    (``cosim.master.AdaptiveStep``), starting from step_s."""
    step_min_s: number(1e-3, 5.0, unit="s") = 0.125
    """Smallest adaptive step [s]: step_s divided by a power of two."""
    step_max_s: number(1e-3, 60.0, unit="s") = 2.0
    """Largest adaptive step [s]: step_s times a power of two."""

    @model_validator(mode="after")
    def _complete(self):
        if self.record_every_s is None:
            self.record_every_s = self.step_s
        if self.record_every_s < self.step_s:
            raise refuse("record_every_s", f"finite and >= {self.step_s:g} and <= 3600 s "
                         "(step_s)", f"got {self.record_every_s!r}")
        if self.communication_step == "adaptive":
            if self.coupling_tolerance is None:
                raise refuse("coupling_tolerance", "in (0, 1] for communication_step = "
                             "\"adaptive\"", "none declared")
            if not self.coupling_signals:
                raise refuse("coupling_signals", "one or more component.output names for "
                             "communication_step = \"adaptive\"", "none declared")
            from cosim.master import ladder_exponent

            for key, limit, side, example in (
                    ("step_min_s", self.step_min_s, "<=", self.step_s / 4),
                    ("step_max_s", self.step_max_s, ">=", self.step_s * 4)):
                exponent = ladder_exponent(limit, self.step_s)
                if exponent is None or (exponent > 0 if side == "<=" else exponent < 0):
                    raise refuse(key, f"step_s {self.step_s:g} s times a power of two, "
                                 f"{side} step_s (e.g. {example:g} s)", f"got {limit!r}")
            ratio = self.record_every_s / self.step_max_s
            if abs(ratio - round(ratio)) > 1e-9 or ratio < 1:
                # every recording time is then a step's end, however the step varies
                raise refuse("record_every_s", f"a whole multiple of step_max_s "
                             f"{self.step_max_s:g} s for communication_step = \"adaptive\"",
                             f"got {self.record_every_s!r}")
        return self


def _endpoint(value):
    if not isinstance(value, str) or value.count(".") != 1 or not all(value.split(".")):
        raise PydanticCustomError("minetwin", "must be {allowed}", {
            "key": "", "allowed": "'ASSET.PORT' (an asset name and one of its ports)",
            "detail": f"got {value!r}"})
    return value


Endpoint = Annotated[str, BeforeValidator(_endpoint)]


class FlowParameters(Parameters):
    """Particles leaving ``from`` (ASSET.OUTLET) enter ``to`` (ASSET.INLET)."""

    source: Endpoint = Field(alias="from")
    target: Endpoint = Field(alias="to")
    fraction: number(0.0, 1.0, low_open=True) = 1.0
    """Share of the outlet's mass [-] when several flows leave it (they add up to 1)."""


class SignalParameters(Parameters):
    """The output ``from`` (COMPONENT.OUTPUT) is the input ``to`` (COMPONENT.INPUT)."""

    source: Endpoint = Field(alias="from")
    target: Endpoint = Field(alias="to")


class ScenarioParameters(Parameters):
    """The file's tables; each is checked by its own model so that one error does not
    hide the others."""

    simulation: dict = {}
    assets: dict[str, dict]
    flows: list[dict] = []
    signals: list[dict] = []
    reference: dict | None = None
    """Names the signals of a reference result (minetwin.testing.reference); the simulator
    ignores it."""


def _flow_ends(flow: dict) -> dict:
    source, outlet = flow["from"].split(".")
    target, inlet = flow["to"].split(".")
    return {"from_asset": source, "from_port": outlet, "to_asset": target, "to_port": inlet,
            "fraction": flow["fraction"]}


def validate(raw: dict) -> dict:
    """Check a scenario dict (as read from TOML) and fill in the defaults.

    The result has the same keys as the file (plus defaults), so ``validate``
    is idempotent and a validated scenario may be edited (e.g. by
    ``reproduce``) and validated again. Every error found is reported at once.
    """
    return _validated(raw)[0]


def _validated(raw: dict):
    """``(config, PlantSpec)`` of a scenario dict (``validate``)."""
    from cosim.kinds import PlantSpec, asset_kind

    if not isinstance(raw, dict):
        raise ValidationError("scenario", "a table of tables", f"got {type(raw).__name__}")
    top, errors = check(ScenarioParameters, raw)
    if top is None:
        raise_all(errors)
    simulation, errors = check(SimulationParameters, top.simulation, "simulation")
    checked = [(check(FlowParameters, flow, f"flows[{k}]"), "flow")
               for k, flow in enumerate(top.flows)]
    checked += [(check(SignalParameters, signal, f"signals[{k}]"), "signal")
                for k, signal in enumerate(top.signals)]
    for (_, found), _ in checked:
        errors += found
    flow_tables = [table for (table, _), what in checked if what == "flow"]
    signal_tables = [table for (table, _), what in checked if what == "signal"]
    spec = PlantSpec()
    assets = {}
    if not top.assets:
        errors.append(ValidationError("assets", "at least one [assets.NAME] table"))
    for name, table in top.assets.items():
        path = f"assets.{name}"
        if "." in name:
            errors.append(ValidationError(path, "a name without '.'", f"got {name!r}"))
            continue
        try:
            kind = asset_kind(table.get("kind"), f"{path}.kind")
        except ValidationError as exc:
            errors.append(exc)
            continue
        parameters, found = check(kind.Parameters,
                                  {k: v for k, v in table.items() if k != "kind"}, path)
        errors += found
        if parameters is not None:
            spec.assets[name] = (kind, parameters)
            spec.kind_names[name] = table["kind"]
            assets[name] = {"kind": table["kind"], **parameters.model_dump()}
    flows = [flow.model_dump(by_alias=True) for flow in flow_tables if flow is not None]
    spec.flows = [_flow_ends(flow) for flow in flows]
    complete = len(spec.assets) == len(top.assets) and len(flows) == len(flow_tables)
    errors += _check_flows(spec, flows, top.assets, complete)
    for k, signal in enumerate(signal_tables):
        if signal is None:
            continue
        for key, end in (("from", signal.source), ("to", signal.target)):
            if end.split(".")[0] not in top.assets and not _owned_component(end, top.assets):
                errors.append(ValidationError(f"signals[{k}].{key}",
                                              f"'ASSET.SIGNAL' with an asset among "
                                              f"{list(top.assets)}", f"got {end!r}"))
    if complete:
        for name, (kind, parameters) in spec.assets.items():
            errors += kind.check(name, parameters, spec)
    raise_all(errors)
    cfg = {"simulation": simulation.model_dump(), "assets": assets, "flows": flows,
           "signals": [signal.model_dump(by_alias=True) for signal in signal_tables]}
    if top.reference is not None:
        cfg["reference"] = top.reference
    return cfg, spec


def _owned_component(end: str, assets: dict) -> bool:
    """An FMU of an asset (``crusher_fmu.power``) may be a signal's end too."""
    component = end.split(".")[0]
    return component.endswith("_fmu") and component[:-len("_fmu")] in assets


def _check_flows(spec, flows, declared, complete) -> list[ValidationError]:
    errors = []
    routed: dict[tuple[str, str], float] = {}
    for k, flow in enumerate(spec.flows):
        for key, asset, port, side in (("from", flow["from_asset"], flow["from_port"], 1),
                                       ("to", flow["to_asset"], flow["to_port"], 0)):
            path = f"flows[{k}].{key}"
            if asset not in declared:
                errors.append(ValidationError(path, f"'ASSET.PORT' with an asset among "
                                              f"{list(declared)}", f"got {flows[k][key]!r}"))
                continue
            if asset not in spec.assets:
                continue                # the asset's own table is in error
            kind, parameters = spec.assets[asset]
            ports = kind.ports(parameters)[side]
            if port not in ports:
                what = "outlet" if side else "inlet"
                errors.append(ValidationError(
                    path, f"an {what} of {asset} ({spec.kind_names[asset]}): one of "
                    f"{list(ports)}" if ports else f"an {what}: {asset} "
                    f"({spec.kind_names[asset]}) has none", f"got {flows[k][key]!r}"))
            elif side:
                key_ = (asset, port)
                routed[key_] = routed.get(key_, 0.0) + flow["fraction"]
    for (asset, port), total in routed.items():
        if abs(total - 1.0) > 1e-9:
            errors.append(ValidationError(f"flows (from {asset}.{port})",
                                          "fractions adding up to 1", f"they add up to {total:g}"))
    if complete:
        for asset, (kind, parameters) in spec.assets.items():
            for outlet in kind.ports(parameters)[1]:
                if (asset, outlet) not in routed:
                    errors.append(ValidationError(
                        "flows", f"a flow from {asset}.{outlet}", "the outlet is not connected"))
    return errors


def load(path) -> dict:
    """Read and validate a scenario TOML file."""
    from cosim.tomlfile import read_toml

    return validate(read_toml(path, "scenario"))


def assets_of_kind(config: dict, kind: str) -> list[str]:
    """Names of the scenario's assets of ``kind``, in order."""
    return [name for name, table in config["assets"].items() if table["kind"] == kind]


# ---------------------------------------------------------------------- build
@dataclass
class Simulation:
    """A built scenario: the master, the shared plant and the assets by name."""

    config: dict
    master: object
    plant: object
    assets: dict = field(default_factory=dict)
    events_path: str | None = None

    def run(self, until: float | None = None) -> "Simulation":
        """Run to ``until`` [s] (default: the scenario's ``simulation.until_s``)."""
        self.master.run(self.config["simulation"]["until_s"] if until is None else until)
        return self

    def close(self) -> None:
        """Release the FMUs and flush/close the event store."""
        self.master.finish()
        if self.plant.events is not None:
            self.plant.flush_events()
            self.plant.events.close()
            self.plant.events = None

    @property
    def timeseries(self):
        return self.master.timeseries


def build(config: dict, *, seed: int | None = None, storage_model: str | None = None,
          events_path=None, progress: bool = False) -> Simulation:
    """Build the plant of a (validated or raw) scenario dict.

    ``seed`` overrides the scenario's, ``storage_model`` every stockpile's;
    ``events_path`` is the SQLite event store (None: events are not recorded).
    Assets are built and added to the master in the scenario's order, then
    the flows and the signals are wired (both ends checked).
    """
    from cosim.assets import Plant, PlantBalance
    from cosim.events import EventStore
    from cosim.kinds import BuildContext
    from cosim.master import AdaptiveStep, Master
    from cosim.particles import ParticleStore

    cfg = copy.deepcopy(config)
    if seed is not None:
        cfg.setdefault("simulation", {})["seed"] = int(seed)
    if storage_model is not None:
        for table in cfg.get("assets", {}).values():
            if isinstance(table, dict) and table.get("kind") == "stockpile":
                table["model"] = storage_model
    cfg, spec = _validated(cfg)
    sim = cfg["simulation"]
    rng = np.random.default_rng(sim["seed"])
    events = (EventStore(events_path, timeout=sim["event_store_timeout_s"])
              if events_path is not None else None)
    plant = Plant(ParticleStore(capacity=4096), events, rng)
    adaptive = (AdaptiveStep(sim["coupling_signals"], sim["coupling_tolerance"],
                             sim["step_min_s"], sim["step_max_s"])
                if sim["communication_step"] == "adaptive" else None)
    master = Master(step=sim["step_s"], record_every=max(int(round(sim["record_every_s"]
                                                                   / sim["step_s"])), 1),
                    progress=progress, adaptive=adaptive)
    context = BuildContext(plant=plant, master=master, simulation=sim, spec=spec)
    for name, (kind, parameters) in spec.assets.items():
        context.built[name] = kind.build(name, parameters, context)
    master.add(PlantBalance(plant))
    errors = []
    for k, flow in enumerate(spec.flows):
        target = context.built[flow["to_asset"]][0]
        for source in context.built[flow["from_asset"]]:
            try:
                master.connect_flow(source, flow["from_port"], target, flow["to_port"],
                                    flow["fraction"])
            except ValidationError as exc:
                errors.append(ValidationError(f"flows[{k}]", exc.allowed, exc.detail))
    components = {c.name: c for c in master.components}
    for k, signal in enumerate(cfg["signals"]):
        (source, output), (target, input) = (end.split(".") for end in (signal["from"],
                                                                       signal["to"]))
        try:
            master.connect(components[source], output, components[target], input)
        except (ValidationError, KeyError) as exc:
            errors.append(ValidationError(f"signals[{k}]", getattr(
                exc, "allowed", f"a component among {sorted(components)}"),
                getattr(exc, "detail", f"got {exc}")))
    if errors:
        master.finish()
    raise_all(errors)
    assets = {c.name: c for c in master.components}
    return Simulation(cfg, master, plant, assets,
                      None if events_path is None else str(events_path))


# --------------------------------------------------------------------- outputs
def summarize(simulation: Simulation) -> dict:
    """The run's summary: sizes, mass balance, timing and the main signals' means."""
    from cosim.fmu import FmuComponent  # (fmpy) not at the import of this module

    series = simulation.timeseries
    plant = simulation.plant
    master = simulation.master
    held = float(plant.particles.mass.sum())
    removed = plant.removed_ids
    summary = {
        "simulated_s": float(master.time),
        "wall_s": float(master.wall_s),
        "realtime_factor": float(master.time / master.wall_s) if master.wall_s > 0 else None,
        "seed": int(simulation.config["simulation"]["seed"]),
        "storage_model": next(((simulation.assets[name].fidelity or {}).get(
            "model", simulation.config["assets"][name]["model"])
            for name in assets_of_kind(simulation.config, "stockpile")), None),
        "fidelity": {name: simulation.assets[name].fidelity
                     for name in assets_of_kind(simulation.config, "stockpile")
                     if simulation.assets[name].fidelity is not None},
        "step_s": float(master.step),
        "communication_steps": master.step_statistics(),  # count, min, max, mean [s]
        "particles_created": int(plant.particles_created),
        "particles_in_plant": int(len(plant.particles)),
        "particles_out": int(removed.size),
        "mass_in_kg": float(plant.mass_in),
        "mass_out_kg": float(plant.mass_out),
        "mass_held_kg": held,
        "mass_balance_rel_error": float(series["plant.mass_balance_rel_error"].max())
        if len(series) else 0.0,
        "stopped_by": master.stopped,  # None, or the component that requested the stop and why
        "fmus": {component.name: str(component.path) for component in master.components
                 if isinstance(component, FmuComponent)},  # which file each FMU ran from
    }
    crusher, pile, mill = (next(iter(assets_of_kind(simulation.config, kind)), kind)
                           for kind in ("crusher", "stockpile", "mill"))
    means = {"crusher_power_mean_w": f"{crusher}_fmu.power",
             "mill_power_mean_w": f"{mill}_fmu.power",
             "crusher_zone_hardness_mean": f"{crusher}.zone_hardness",
             "mill_hardness_mean": f"{mill}.hardness"}
    for key, column in means.items():
        if column in series:
            values = series[column].to_numpy()
            finite = values[np.isfinite(values)]
            summary[key] = float(finite.mean()) if finite.size else None
    for key, column in {"stockpile_mass_max_kg": f"{pile}.mass_kg",
                        "mill_mass_max_kg": f"{mill}.mass_kg"}.items():
        if column in series:
            summary[key] = float(series[column].max()) if len(series) else None
    return summary


def write_outputs(simulation: Simulation, out_dir, failure=None,
                  scenario_name: str | None = None) -> dict:
    """Write timeseries.parquet, summary.json and PNG plots to ``out_dir`` (overview.png;
    fidelity_NAME.png for a ``model = "auto"`` stockpile); the summary.

    After a failed run (``failure``) they hold what was recorded up to it, and the
    summary's ``failed`` says why. ``scenario_name`` titles the figures."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    series = simulation.timeseries
    series.to_parquet(out / "timeseries.parquet")
    summary = summarize(simulation)
    summary["failed"] = None if failure is None else str(failure)
    jsonio.write(out / "summary.json", summary, indent=2, sort_keys=True)
    from cosim.plotstyle import run_label

    run = run_label(simulation.config, scenario=scenario_name)
    plot_overview(series, out / "overview.png", run=run,
                  assets={kind: assets_of_kind(simulation.config, kind)
                          for kind in ("crusher", "stockpile", "mill")})
    if summary["fidelity"]:
        from cosim.fidelity_plot import plot_fidelity

        for pile, choice in summary["fidelity"].items():
            plot_fidelity(choice, out / f"fidelity_{pile}.png", series=series, pile=pile,
                          run=run)
    return summary


def plot_overview(series, path, run: str | None = None, assets: dict | None = None) -> None:
    """Four panels: crusher power and zone hardness, stockpile mass, mill power and
    hardness, one line per asset of each kind; titled with ``run``
    (``cosim.plotstyle.run_label``). ``assets``: kind -> asset names (default: the
    paper's names crusher, stockpile, mill)."""
    from cosim import plotstyle

    assets = assets or {"crusher": ["crusher"], "stockpile": ["stockpile"], "mill": ["mill"]}
    crushers, piles, mills = (assets.get(kind, []) for kind in ("crusher", "stockpile", "mill"))
    plt = plotstyle.pyplot()
    t = series.index.to_numpy()
    fig, axes = plt.subplots(4, 1, figsize=(9, 10.5), sharex=True)
    panels = [
        (axes[0], [(f"{c}_fmu.power", f"{c} power") for c in crushers], 1e-3,
         "crusher power [kW]"),
        (axes[1], [(f"{c}.zone_hardness_avg", f"{c} zone hardness (30 s average)")
                   for c in crushers], 1.0, "crusher zone hardness [-]"),
        (axes[2], [(f"{p}.mass_kg", f"{p} mass") for p in piles], 1e-3, "stockpile mass [t]"),
        (axes[3], [(f"{m}_fmu.power", f"{m} power") for m in mills], 1e-6, "mill power [MW]"),
    ]
    for ax, lines, scale, label in panels:
        for column, name in lines:
            if column in series:
                ax.plot(t, series[column].to_numpy() * scale, lw=0.8, label=name)
        ax.set_ylabel(label)
    for ax in axes[1:3]:
        plotstyle.legend(ax, loc="upper left")
    # hardness is relative to the reference ore (1): a span of at least 0.5
    # keeps a rise of a few parts per thousand from filling the axis
    zone = [series[f"{c}.zone_hardness_avg"] for c in crushers
            if f"{c}.zone_hardness_avg" in series]
    plotstyle.span_at_least(axes[1], np.concatenate(zone) if zone else [], 0.5)
    twins = []
    hardness = [(m, series[f"{m}.hardness_avg"].to_numpy()) for m in mills
                if f"{m}.hardness_avg" in series]
    if hardness:
        twin = axes[3].twinx()
        twin.grid(False)
        for (mill, values), color in zip(hardness, ("tab:red", "tab:purple", "tab:brown")):
            twin.plot(t, values, color=color, lw=0.8,
                      label=f"{mill} hardness (30 s average, right axis)")
        twin.set_ylabel("mill hardness [-]", color="tab:red")
        twin.ticklabel_format(axis="y", useOffset=False)
        plotstyle.span_at_least(twin, np.concatenate([v for _, v in hardness]), 0.5)
        twins.append(twin)
    plotstyle.legend(axes[0], loc="upper left")
    plotstyle.legend(axes[3], *twins, loc="upper left")
    axes[-1].set_xlabel("time [s]")
    plotstyle.title(fig, "Mine-to-mill overview", run)
    fig.tight_layout()
    plotstyle.save(fig, path)


def run_scenario(config: dict, out_dir=None, *, until: float | None = None,
                 seed: int | None = None, storage_model: str | None = None,
                 progress: bool = False, before_run=None,
                 scenario_name: str | None = None) -> tuple[Simulation, dict]:
    """Build, run and (with ``out_dir``) write a scenario; returns (simulation, summary).

    ``before_run`` is called with the built ``Simulation`` before it runs
    (e.g. to serve its stockpile over REST). The FMUs are released and the
    event store closed before returning.
    """
    events_path = None
    if out_dir is not None:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        events_path = Path(out_dir) / "events.sqlite"
        for suffix in ("", "-wal", "-shm"):
            Path(str(events_path) + suffix).unlink(missing_ok=True)
    simulation = build(config, seed=seed, storage_model=storage_model,
                       events_path=events_path, progress=progress)
    if before_run is not None:
        before_run(simulation)
    from cosim.master import CosimulationError

    started = wallclock.perf_counter()
    failure = None
    try:
        simulation.run(until)
    except CosimulationError as exc:
        failure = exc
    finally:
        try:
            simulation.close()
        except CosimulationError as exc:  # e.g. the event store: the other outputs still count
            failure = failure or exc
    simulation.master.wall_s = wallclock.perf_counter() - started
    summary = (write_outputs(simulation, out_dir, failure=failure, scenario_name=scenario_name)
               if out_dir is not None
               else summarize(simulation))
    if failure is not None:
        raise failure
    return simulation, summary
