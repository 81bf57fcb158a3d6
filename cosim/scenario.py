"""Scenarios of the 2D mine simulator: load a TOML file, validate, build, run, write.

Source: paper section "Simulator" (the plant: two sources, haul trucks, a jaw
crusher, belt conveyors, a stockpile and a mill) and section "Results",
"Step response" (the experiments). The plant topology is fixed (the
paper's mine); a scenario file sets every parameter, each with its unit in
the key name (``_m``, ``_s``, ``_kg``, ``_kg_s``, ``_m_s``, ``_rad_s``) and
the file's comments cite the paper. See ``examples/step_response.toml``.

Tables and keys (defaults in brackets):

``[simulation]`` until_s [1200], step_s [0.5], record_every_s [= step_s],
    seed [1], sensor_window_s [30], event_store_timeout_s [30]: how long a write
    waits for another process that holds the event store's lock. The communication step 0.5 s resolves the
    fastest material dynamics of the plant: a particle stays about 1 s in the
    crusher zone (785 kg at 1 t/s) and the trucks dump every 27.5 s; the FMUs'
    physics (crusher torque, mill speed with a 5 s time constant, mill
    breakage with an exponential integrator) is smooth over it.
``[sources.NAME]`` (one or more) loading_point_m, ore_body_origin_m [= loading
    point], grade, hardness (table: kind = "constant" | "step" |
    "quadratic" and its parameters, see ``cosim.blockmodel``), length_m,
    face_width_m, face_height_m, block_length_m [1], density_kg_m3 [2700],
    particle_mass_kg [100], particle_mass_spread [0.5], blast (table: x50_m
    [0.1], x_max_m [1.0], b [2.0], x50_spread [0.15])
``[[trucks]]`` name, route (list of source names), payload_kg [15000],
    speed_m_s [8], load_time_s [6], dump_time_s [2.75], start_s [0]
``[crusher]`` position_m, fmu ["crusher": a built FMU name or an .fmu path],
    speed_rad_s [10], zone_capacity_kg [900], jaw_throughput_kg_s [1000],
    parameters (table of FMU parameters)
``[conveyors.crusher_to_stockpile]``, ``[conveyors.stockpile_to_mill]``
    length_m, speed_m_s [2], bin_length_m [1]
``[stockpile]`` position_m, outlet_m [= position], model ["fifo"], options
    (table passed to the storage model), capacity_kg [2e6], discharge (list
    of [time_s, rate_kg_s], [[0, 0]]), initial_mass_kg [0]: ore mined and
    crushed before t = 0 (see ``fill_stockpile``)
``[mill]`` position_m, fmu ["mill"], speed_rad_s [1.2],
    product_threshold_kg [0.01], product_event_interval_s [60],
    update_interval_s [0: every step], parameters

A value outside its range, a missing required key or an unknown key is a
``ValidationError`` naming the dotted key (e.g. ``sources.left.grade``).
"""

from __future__ import annotations

import copy
import time as wallclock
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cosim import jsonio
from cosim.errors import ValidationError
from cosim.storage import check_storage_options

REQUIRED = object()
MAX_LENGTH_M = 100_000.0
"""Longest ore body, face, belt or block [m] a scenario may set (100 km)."""
MAX_BLOCKS = 1_000_000
"""Most block-model cells along a source, and bins along a belt (each costs memory)."""
MAX_PARTICLES_PER_LOAD = 100_000
"""Most pseudo-particles in one truckload (payload_kg / particle_mass_kg; paper: ~150)."""
WALL_CLOCK_FIELDS = ("wall_s", "realtime_factor")
"""Summary fields that depend on the machine, not on the scenario and seed."""


# ------------------------------------------------------------------ validation
def _number(table: dict, key: str, path: str, default=REQUIRED, *, low=None, high=None,
            low_open=False, unit="", integer=False) -> float:
    name = f"{path}.{key}"
    if key not in table:
        if default is REQUIRED:
            raise ValidationError(name, "given", "missing required key")
        return default
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValidationError(name, f"a number{' [' + unit + ']' if unit else ''}",
                              f"got {value!r}")
    if integer and not float(value).is_integer():
        raise ValidationError(name, "an integer", f"got {value!r}")
    value = int(value) if integer else float(value)
    parts = ["finite"]
    if low is not None:
        parts.append(f"{'>' if low_open else '>='} {low:g}")
    if high is not None:
        parts.append(f"<= {high:g}")
    ok = np.isfinite(value) and (low is None or (value > low if low_open else value >= low)) \
        and (high is None or value <= high)
    if not ok:
        raise ValidationError(name, " and ".join(parts) + (f" {unit}" if unit else ""),
                              f"got {value!r}")
    return value


def _vector(table: dict, key: str, path: str, default=REQUIRED) -> list[float]:
    name = f"{path}.{key}"
    if key not in table:
        if default is REQUIRED:
            raise ValidationError(name, "given", "missing required key")
        return list(default)
    value = table[key]
    ok = isinstance(value, list) and len(value) in (2, 3) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)
        for v in value)
    if not ok:
        raise ValidationError(name, "a list of 2 or 3 finite coordinates [m]", f"got {value!r}")
    return [float(v) for v in value] + [0.0] * (3 - len(value))


def _string(table: dict, key: str, path: str, default=REQUIRED, choices=None) -> str:
    name = f"{path}.{key}"
    if key not in table:
        if default is REQUIRED:
            raise ValidationError(name, "given", "missing required key")
        return default
    value = table[key]
    if not isinstance(value, str) or (choices is not None and value not in choices):
        raise ValidationError(name, f"one of {list(choices)}" if choices else "a string",
                              f"got {value!r}")
    return value


def _table(parent: dict, key: str, path: str, default=REQUIRED) -> dict:
    name = f"{path}.{key}" if path else key
    if key not in parent:
        if default is REQUIRED:
            raise ValidationError(name, "given (a table)", "missing required table")
        return dict(default)
    value = parent[key]
    if not isinstance(value, dict):
        raise ValidationError(name, "a table", f"got {value!r}")
    return value


def _no_unknown(table: dict, allowed, path: str) -> None:
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise ValidationError(f"{path}.{unknown[0]}" if path else unknown[0],
                              f"one of {sorted(allowed)}", "unknown key")


def _hardness(table: dict, path: str) -> dict:
    from cosim.blockmodel import hardness_function

    spec = _table(table, "hardness", path)
    name = f"{path}.hardness"
    for key, value in spec.items():
        if key != "kind" and (isinstance(value, bool) or not isinstance(value, (int, float))
                              or not np.isfinite(value)):
            raise ValidationError(f"{name}.{key}", "a finite number", f"got {value!r}")
    try:
        profile = hardness_function(spec)
    except ValidationError as exc:
        raise ValidationError(f"{name}.{exc.field.split('.')[-1]}", exc.allowed) from None
    probe = profile(np.linspace(0.0, 1000.0, 101))
    if not np.all(probe > 0):
        raise ValidationError(name, "a profile with hardness > 0 everywhere",
                              f"min {probe.min():g}")
    return dict(spec)


def _source(table: dict, path: str) -> dict:
    _no_unknown(table, ("loading_point_m", "ore_body_origin_m", "grade", "hardness", "length_m",
                        "face_width_m", "face_height_m", "block_length_m", "density_kg_m3",
                        "particle_mass_kg", "particle_mass_spread", "blast"), path)
    out = {"loading_point_m": _vector(table, "loading_point_m", path)}
    out["ore_body_origin_m"] = _vector(table, "ore_body_origin_m", path, out["loading_point_m"])
    out["grade"] = _number(table, "grade", path, low=0.0, high=1.0)
    out["hardness"] = _hardness(table, path)
    out["length_m"] = _number(table, "length_m", path, low=0.0, low_open=True,
                              high=MAX_LENGTH_M, unit="m")
    out["face_width_m"] = _number(table, "face_width_m", path, low=0.0, low_open=True,
                                  high=MAX_LENGTH_M, unit="m")
    out["face_height_m"] = _number(table, "face_height_m", path, low=0.0, low_open=True,
                                   high=MAX_LENGTH_M, unit="m")
    out["block_length_m"] = _number(table, "block_length_m", path, 1.0, low=0.0,
                                    low_open=True, high=MAX_LENGTH_M, unit="m")
    smallest_block = out["length_m"] / MAX_BLOCKS
    if out["block_length_m"] < smallest_block:
        raise ValidationError(f"{path}.block_length_m",
                              f">= {smallest_block:g} m (length_m / {MAX_BLOCKS:,} blocks)",
                              f"got {out['block_length_m']!r}")
    out["density_kg_m3"] = _number(table, "density_kg_m3", path, 2700.0, low=100.0,
                                   high=20000.0, unit="kg/m^3")
    out["particle_mass_kg"] = _number(table, "particle_mass_kg", path, 100.0, low=0.0,
                                      low_open=True, high=1e5, unit="kg")
    out["particle_mass_spread"] = _number(table, "particle_mass_spread", path, 0.5, low=0.0,
                                          high=0.99)
    blast = _table(table, "blast", path, {})
    bpath = f"{path}.blast"
    _no_unknown(blast, ("x50_m", "x_max_m", "b", "x50_spread"), bpath)
    x_max = _number(blast, "x_max_m", bpath, 1.0, low=1e-4, high=10.0, unit="m")
    out["blast"] = {
        "x50_m": _number(blast, "x50_m", bpath, 0.1, low=1e-5, high=x_max, low_open=True,
                         unit="m"),
        "x_max_m": x_max,
        "b": _number(blast, "b", bpath, 2.0, low=0.0, low_open=True, high=20.0),
        "x50_spread": _number(blast, "x50_spread", bpath, 0.15, low=0.0, high=2.0),
    }
    return out


def _conveyor(table: dict, path: str) -> dict:
    _no_unknown(table, ("length_m", "speed_m_s", "bin_length_m"), path)
    length = _number(table, "length_m", path, low=0.0, low_open=True, high=MAX_LENGTH_M,
                     unit="m")
    return {"length_m": length,
            "speed_m_s": _number(table, "speed_m_s", path, 2.0, low=0.0, high=20.0,
                                 unit="m/s"),
            "bin_length_m": _number(table, "bin_length_m", path, min(1.0, length),
                                    low=length / MAX_BLOCKS, high=length, unit="m")}


def _parameters(table: dict, path: str) -> dict:
    """FMU parameters as given (numbers, booleans, strings, or lists of them): the FMU
    checks each against its variable's type when it loads (cosim.fmu)."""
    params = _table(table, "parameters", path, {})
    for key, value in params.items():
        items = value if isinstance(value, list) else [value]
        for item in items:
            if not isinstance(item, (bool, int, float, str)) or (
                    isinstance(item, float) and not np.isfinite(item)):
                raise ValidationError(f"{path}.parameters.{key}",
                                      "a finite number, a boolean, a string or a list of them",
                                      f"got {value!r}")
    return dict(params)


def validate(raw: dict) -> dict:
    """Check a scenario dict (as read from TOML) and fill in the defaults.

    The result has the same keys as the file, so ``validate`` is idempotent
    and a validated scenario may be edited (e.g. by ``reproduce``) and
    validated again.
    """
    from cosim.storage import MAX_DISCHARGE_RATE, registered_models

    if not isinstance(raw, dict):
        raise ValidationError("scenario", "a table of tables", f"got {type(raw).__name__}")
    # [reference] names the signals of a reference result (minetwin.testing.reference);
    # the simulator ignores it
    _no_unknown(raw, ("simulation", "sources", "trucks", "crusher", "conveyors", "stockpile",
                      "mill", "reference"), "")
    cfg: dict = {}
    sim = _table(raw, "simulation", "", {})
    _no_unknown(sim, ("until_s", "step_s", "record_every_s", "seed", "sensor_window_s",
                      "event_store_timeout_s"), "simulation")
    step = _number(sim, "step_s", "simulation", 0.5, low=1e-3, high=5.0, unit="s")
    cfg["simulation"] = {
        "until_s": _number(sim, "until_s", "simulation", 1200.0, low=0.0, high=1e7, unit="s"),
        "step_s": step,
        "record_every_s": _number(sim, "record_every_s", "simulation", step, low=step,
                                  high=3600.0, unit="s"),
        "seed": _number(sim, "seed", "simulation", 1, low=0, high=2**63 - 1, integer=True),
        "sensor_window_s": _number(sim, "sensor_window_s", "simulation", 30.0, low=0.0,
                                   high=3600.0, unit="s"),
        "event_store_timeout_s": _number(sim, "event_store_timeout_s", "simulation", 30.0,
                                         low=0.0, high=3600.0, unit="s"),
    }
    sources = _table(raw, "sources", "")
    if not sources:
        raise ValidationError("sources", "at least one [sources.NAME] table")
    cfg["sources"] = {name: _source(_table(sources, name, "sources"), f"sources.{name}")
                      for name in sources}
    trucks = raw.get("trucks")
    if not isinstance(trucks, list) or not trucks or not all(isinstance(t, dict) for t in trucks):
        raise ValidationError("trucks", "a non-empty array of [[trucks]] tables",
                              f"got {trucks!r}")
    cfg["trucks"] = []
    for k, truck in enumerate(trucks):
        path = f"trucks[{k}]"
        _no_unknown(truck, ("name", "route", "payload_kg", "speed_m_s", "load_time_s",
                            "dump_time_s", "start_s"), path)
        route = truck.get("route")
        if not isinstance(route, list) or not route or any(r not in cfg["sources"]
                                                           for r in route):
            raise ValidationError(f"{path}.route", f"a non-empty list of source names among "
                                  f"{sorted(cfg['sources'])}", f"got {route!r}")
        cfg["trucks"].append({
            "name": _string(truck, "name", path, f"truck_{k + 1}"),
            "route": list(route),
            "payload_kg": _number(truck, "payload_kg", path, 15000.0, low=0.0, low_open=True,
                                  high=1e6, unit="kg"),
            "speed_m_s": _number(truck, "speed_m_s", path, 8.0, low=0.0, low_open=True,
                                 high=50.0, unit="m/s"),
            "load_time_s": _number(truck, "load_time_s", path, 6.0, low=0.0, low_open=True,
                                   high=3600.0, unit="s"),
            "dump_time_s": _number(truck, "dump_time_s", path, 2.75, low=0.0, low_open=True,
                                   high=3600.0, unit="s"),
            "start_s": _number(truck, "start_s", path, 0.0, low=0.0, high=1e7, unit="s"),
        })
    for k, truck in enumerate(cfg["trucks"]):
        for name in truck["route"]:
            lightest = truck["payload_kg"] / MAX_PARTICLES_PER_LOAD
            if cfg["sources"][name]["particle_mass_kg"] < lightest:
                raise ValidationError(
                    f"sources.{name}.particle_mass_kg",
                    f">= {lightest:g} kg (trucks[{k}].payload_kg / "
                    f"{MAX_PARTICLES_PER_LOAD:,} particles per load)",
                    f"got {cfg['sources'][name]['particle_mass_kg']!r}")
    names = [t["name"] for t in cfg["trucks"]]
    if len(set(names)) != len(names):
        raise ValidationError("trucks.name", "unique", f"got {names}")
    crusher = _table(raw, "crusher", "")
    _no_unknown(crusher, ("position_m", "fmu", "speed_rad_s", "zone_capacity_kg",
                          "jaw_throughput_kg_s", "parameters"), "crusher")
    cfg["crusher"] = {
        "position_m": _vector(crusher, "position_m", "crusher"),
        "fmu": _string(crusher, "fmu", "crusher", "crusher"),
        "speed_rad_s": _number(crusher, "speed_rad_s", "crusher", 10.0, low=0.0, high=1000.0,
                               unit="rad/s"),
        "zone_capacity_kg": _number(crusher, "zone_capacity_kg", "crusher", 900.0, low=0.0,
                                    low_open=True, high=1e6, unit="kg"),
        "jaw_throughput_kg_s": _number(crusher, "jaw_throughput_kg_s", "crusher", 1000.0,
                                       low=0.0, low_open=True, high=1e5, unit="kg/s"),
        "parameters": _parameters(crusher, "crusher"),
    }
    conveyors = _table(raw, "conveyors", "")
    _no_unknown(conveyors, ("crusher_to_stockpile", "stockpile_to_mill"), "conveyors")
    cfg["conveyors"] = {name: _conveyor(_table(conveyors, name, "conveyors"),
                                        f"conveyors.{name}")
                        for name in ("crusher_to_stockpile", "stockpile_to_mill")}
    pile = _table(raw, "stockpile", "")
    _no_unknown(pile, ("position_m", "outlet_m", "model", "options", "capacity_kg",
                       "discharge", "initial_mass_kg"), "stockpile")
    discharge = pile.get("discharge", [[0.0, 0.0]])
    ok = isinstance(discharge, list) and discharge and all(
        isinstance(row, list) and len(row) == 2 for row in discharge)
    if not ok:
        raise ValidationError("stockpile.discharge", "a non-empty list of [time_s, rate_kg_s]",
                              f"got {discharge!r}")
    rows = []
    for k, (t, rate) in enumerate(discharge):
        row = {"t": t, "rate": rate}
        rows.append([_number(row, "t", f"stockpile.discharge[{k}]", low=0.0, unit="s"),
                     _number(row, "rate", f"stockpile.discharge[{k}]", low=0.0,
                             high=MAX_DISCHARGE_RATE, unit="kg/s")])
    position = _vector(pile, "position_m", "stockpile")
    cfg["stockpile"] = {
        "position_m": position,
        "outlet_m": _vector(pile, "outlet_m", "stockpile", position),
        "model": _string(pile, "model", "stockpile", "fifo", choices=list(registered_models())),
        "options": dict(_table(pile, "options", "stockpile", {})),
        "capacity_kg": _number(pile, "capacity_kg", "stockpile", 2.0e6, low=0.0,
                               low_open=True, high=1e9, unit="kg"),
        "discharge": rows,
    }
    check_storage_options(cfg["stockpile"]["model"], cfg["stockpile"]["options"],
                          "stockpile.options")
    cfg["stockpile"]["initial_mass_kg"] = _number(
        pile, "initial_mass_kg", "stockpile", 0.0, low=0.0, high=cfg["stockpile"]["capacity_kg"],
        unit="kg")
    mill = _table(raw, "mill", "")
    _no_unknown(mill, ("position_m", "fmu", "speed_rad_s", "product_threshold_kg",
                       "product_event_interval_s", "update_interval_s", "parameters"), "mill")
    cfg["mill"] = {
        "position_m": _vector(mill, "position_m", "mill"),
        "fmu": _string(mill, "fmu", "mill", "mill"),
        "speed_rad_s": _number(mill, "speed_rad_s", "mill", 1.2, low=0.0, high=100.0,
                               unit="rad/s"),
        "product_threshold_kg": _number(mill, "product_threshold_kg", "mill", 0.01, low=0.0,
                                        low_open=True, high=1e3, unit="kg"),
        "product_event_interval_s": _number(mill, "product_event_interval_s", "mill", 60.0,
                                            low=0.0, low_open=True, high=1e5, unit="s"),
        "update_interval_s": _number(mill, "update_interval_s", "mill", 0.0, low=0.0,
                                     high=60.0, unit="s"),
        "parameters": _parameters(mill, "mill"),
    }
    for asset in ("crusher", "mill"):
        _check_fmu_parameters(cfg[asset]["fmu"], cfg[asset]["parameters"], asset)
    return cfg


def _check_fmu_parameters(fmu: str, parameters: dict, path: str) -> None:
    """Refuse parameters the FMU does not have, or values outside its declared min/max."""
    if not parameters:
        return
    from fmpy import read_model_description

    file = _fmu_file(fmu, path)
    try:
        description = read_model_description(file)
    except Exception:  # noqa: BLE001 - a broken FMU is reported, in full, when it is loaded
        return
    declared = {v.name: v for v in description.modelVariables
                if v.causality in ("parameter", "input") or v.variability == "tunable"}
    for key, value in parameters.items():
        name = f"{path}.parameters.{key}"
        variable = declared.get(key)
        if variable is None:
            raise ValidationError(name, f"a parameter of {Path(file).name}: "
                                  f"one of {sorted(declared)}", "unknown parameter")
        unit = f" {variable.unit}" if variable.unit else ""
        low, high = (None if v is None else float(v) for v in (variable.min, variable.max))
        if (low is not None and value < low) or (high is not None and value > high):
            bounds = " and ".join(part for part in (
                f">= {low:g}{unit}" if low is not None else "",
                f"<= {high:g}{unit}" if high is not None else "") if part)
            raise ValidationError(name, f"{bounds} (the FMU's declared range)",
                                  f"got {value!r}")


def load(path) -> dict:
    """Read and validate a scenario TOML file."""
    from cosim.tomlfile import read_toml

    return validate(read_toml(path, "scenario"))


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


def _fmu_file(name: str, path: str) -> str:
    from cosim.fmu import fmu_path

    if name.endswith(".fmu"):
        if not Path(name).is_file():
            raise ValidationError(f"{path}.fmu", "a built FMU name or an existing .fmu file",
                                  f"{name!r} not found")
        return name
    return str(fmu_path(name))


def _storage(cfg: dict, rng_seed) -> object:
    from cosim.storage import make_storage

    return make_storage(cfg["model"], rng=np.random.default_rng(rng_seed), **cfg["options"])


def build(config: dict, *, seed: int | None = None, storage_model: str | None = None,
          events_path=None, progress: bool = False) -> Simulation:
    """Build the plant of a (validated or raw) scenario dict.

    ``seed`` and ``storage_model`` override the scenario's; ``events_path``
    is the SQLite event store (None: events are not recorded).
    """
    from cosim.assets import Plant, PlantBalance
    from cosim.assets.belt import BeltConveyor
    from cosim.assets.crusher import JawCrusher
    from cosim.assets.mill import Mill
    from cosim.assets.source import Source
    from cosim.assets.stockpile import Stockpile
    from cosim.assets.trucks import HaulTruck
    from cosim.blockmodel import hardness_function
    from cosim.events import EventStore
    from cosim.fmu import CRUSHER_INTERFACE, MILL_INTERFACE, FmuComponent
    from cosim.master import Master
    from cosim.particles import ParticleStore

    cfg = copy.deepcopy(config)
    if seed is not None:
        cfg.setdefault("simulation", {})["seed"] = int(seed)
    if storage_model is not None:
        cfg.setdefault("stockpile", {})["model"] = storage_model
    cfg = validate(cfg)
    sim = cfg["simulation"]
    window = sim["sensor_window_s"]
    sample = sim["record_every_s"]      # virtual sensors sample at the recording interval
    rng = np.random.default_rng(sim["seed"])
    events = (EventStore(events_path, timeout=sim["event_store_timeout_s"])
              if events_path is not None else None)
    plant = Plant(ParticleStore(capacity=4096), events, rng)
    master = Master(step=sim["step_s"], record_every=max(int(round(sim["record_every_s"]
                                                                   / sim["step_s"])), 1),
                    progress=progress)
    assets: dict = {}

    sources = {}
    for name, src in cfg["sources"].items():
        sources[name] = Source(
            name, plant, loading_point=src["loading_point_m"],
            origin=src["ore_body_origin_m"], hardness=hardness_function(src["hardness"]),
            grade=src["grade"], length=src["length_m"], face_width=src["face_width_m"],
            face_height=src["face_height_m"], block_length=src["block_length_m"],
            density=src["density_kg_m3"], particle_mass=src["particle_mass_kg"],
            particle_mass_spread=src["particle_mass_spread"],
            blast={"x50": src["blast"]["x50_m"], "x_max": src["blast"]["x_max_m"],
                   "b": src["blast"]["b"], "x50_spread": src["blast"]["x50_spread"]})
    # Built downstream first (each asset needs its receiver), added upstream
    # first (plant order, so handed-on material is processed in the same step).
    mcfg = cfg["mill"]
    mill = Mill("mill", plant, location=mcfg["position_m"],
                product_threshold=mcfg["product_threshold_kg"],
                product_event_interval=mcfg["product_event_interval_s"],
                update_interval=mcfg["update_interval_s"], sensor_window=window,
                sensor_interval=sample)
    pcfg, c2 = cfg["stockpile"], cfg["conveyors"]["stockpile_to_mill"]
    outlet = pcfg["outlet_m"]
    belt_out = BeltConveyor("conveyor_stockpile_mill", plant, start=outlet,
                            end=mcfg["position_m"], downstream=mill, speed=c2["speed_m_s"],
                            bin_length=c2["bin_length_m"], length=c2["length_m"])
    stockpile = Stockpile("stockpile", plant, model=_storage(pcfg, [sim["seed"], 1]),
                          location=pcfg["position_m"], outlet=outlet, downstream=belt_out,
                          capacity=pcfg["capacity_kg"], discharge=pcfg["discharge"],
                          sensor_window=window, sensor_interval=sample)
    ccfg, c1 = cfg["crusher"], cfg["conveyors"]["crusher_to_stockpile"]
    belt_in = BeltConveyor("conveyor_crusher_stockpile", plant, start=ccfg["position_m"],
                           end=pcfg["position_m"], downstream=stockpile,
                           speed=c1["speed_m_s"], bin_length=c1["bin_length_m"],
                           length=c1["length_m"])
    crusher = JawCrusher("crusher", plant, location=ccfg["position_m"], downstream=belt_in,
                         zone_capacity=ccfg["zone_capacity_kg"],
                         jaw_throughput=ccfg["jaw_throughput_kg_s"], sensor_window=window,
                         sensor_interval=sample)
    trucks = [HaulTruck(t["name"], plant, route=[sources[r] for r in t["route"]],
                        crusher=crusher, payload=t["payload_kg"], speed=t["speed_m_s"],
                        load_time=t["load_time_s"], dump_time=t["dump_time_s"],
                        start=t["start_s"])
              for t in cfg["trucks"]]
    crusher_fmu = FmuComponent(_fmu_file(ccfg["fmu"], "crusher"), interface=CRUSHER_INTERFACE,
                               name="crusher_fmu", parameters=ccfg["parameters"])
    crusher_fmu.set_input("speed", ccfg["speed_rad_s"])
    mill_fmu = FmuComponent(_fmu_file(mcfg["fmu"], "mill"), interface=MILL_INTERFACE,
                            name="mill_fmu", parameters=mcfg["parameters"])
    mill_fmu.set_input("speed_setpoint", mcfg["speed_rad_s"])

    for component in (*sources.values(), *trucks, crusher, crusher_fmu, belt_in, stockpile,
                      belt_out, mill, mill_fmu, PlantBalance(plant)):
        master.add(component)
        assets[component.name] = component
    master.connect(crusher, "zone_hardness_mass", crusher_fmu, "zone_hardness_mass")
    master.connect(crusher_fmu, "fragmentation_map", crusher, "fragmentation_map")
    master.connect(belt_in, "running", crusher, "discharge_enabled")
    master.connect(stockpile, "inlet_open", belt_in, "running")
    master.connect(mill, "charge_mass", mill_fmu, "charge_mass")
    for name in ("breakage_rate", "daughter_fraction", "escape_rate"):
        master.connect(mill_fmu, name, mill, name)
    if pcfg["initial_mass_kg"] > 0:
        fill_stockpile(stockpile, trucks[0], crusher_fmu.outputs()["fragmentation_map"],
                       pcfg["initial_mass_kg"])
    return Simulation(cfg, master, plant, assets,
                      None if events_path is None else str(events_path))


def fill_stockpile(stockpile, truck, fragmentation_map, mass: float) -> None:
    """Put ``mass`` [kg] of earlier production into the stockpile at t = 0.

    The material is what the plant would have made before the run: truck
    loads of ``truck.payload`` [kg] taken in turn from the truck's route
    (the loading faces advance, "appear" events at t = 0) and crushed with
    the crusher FMU's fragmentation map, then received by the stockpile
    ("enter" events at t = 0). It gives the stockpile the paper's scale
    (2,000 t, about 20,000 particles) without simulating the hours of
    filling.
    """
    from cosim.comminution import apply_fragmentation

    store = stockpile.particles
    remaining, k = float(mass), 0
    while remaining > 1e-9:
        load = min(truck.payload, remaining)
        ids = truck.route[k % len(truck.route)].take(load, 0.0)
        slots = store.slots(ids)
        store.f[slots] = apply_fragmentation(store.f[slots], fragmentation_map)
        stockpile.receive(ids, 0.0)
        remaining -= load
        k += 1


# --------------------------------------------------------------------- outputs
def summarize(simulation: Simulation) -> dict:
    """The run's summary: sizes, mass balance, timing and the main signals' means."""
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
        "storage_model": simulation.config["stockpile"]["model"],
        "step_s": float(master.step),
        "particles_created": int(plant.particles_created),
        "particles_in_plant": int(len(plant.particles)),
        "particles_out": int(removed.size),
        "mass_in_kg": float(plant.mass_in),
        "mass_out_kg": float(plant.mass_out),
        "mass_held_kg": held,
        "mass_balance_rel_error": float(series["plant.mass_balance_rel_error"].max())
        if len(series) else 0.0,
        "stopped_by": master.stopped,  # None, or the component that requested the stop and why
    }
    means = {"crusher_power_mean_w": "crusher_fmu.power", "mill_power_mean_w": "mill_fmu.power",
             "crusher_zone_hardness_mean": "crusher.zone_hardness",
             "mill_hardness_mean": "mill.hardness"}
    for key, column in means.items():
        if column in series:
            values = series[column].to_numpy()
            finite = values[np.isfinite(values)]
            summary[key] = float(finite.mean()) if finite.size else None
    for key, column in {"stockpile_mass_max_kg": "stockpile.mass_kg",
                        "mill_mass_max_kg": "mill.mass_kg"}.items():
        if column in series:
            summary[key] = float(series[column].max()) if len(series) else None
    return summary


def write_outputs(simulation: Simulation, out_dir, failure=None,
                  scenario_name: str | None = None) -> dict:
    """Write timeseries.parquet, summary.json and PNG plots to ``out_dir``; the summary.

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

    plot_overview(series, out / "overview.png",
                  run=run_label(simulation.config, scenario=scenario_name))
    return summary


def plot_overview(series, path, run: str | None = None) -> None:
    """Four panels: crusher power and zone hardness, stockpile mass, mill power and
    hardness; titled with ``run`` (``cosim.plotstyle.run_label``)."""
    from cosim import plotstyle

    plt = plotstyle.pyplot()
    t = series.index.to_numpy()
    fig, axes = plt.subplots(4, 1, figsize=(9, 10.5), sharex=True)
    panels = [
        (axes[0], "crusher_fmu.power", 1e-3, "crusher power [kW]", "crusher power"),
        (axes[1], "crusher.zone_hardness_avg", 1.0, "crusher zone hardness [-]",
         "crusher zone hardness (30 s average)"),
        (axes[2], "stockpile.mass_kg", 1e-3, "stockpile mass [t]", "stockpile mass"),
        (axes[3], "mill_fmu.power", 1e-6, "mill power [MW]", "mill power"),
    ]
    for ax, column, scale, label, name in panels:
        if column in series:
            ax.plot(t, series[column].to_numpy() * scale, lw=0.8, label=name)
        ax.set_ylabel(label)
    for ax in axes[1:3]:
        plotstyle.legend(ax, loc="upper left")
    # hardness is relative to the reference ore (1): a span of at least 0.5
    # keeps a rise of a few parts per thousand from filling the axis
    plotstyle.span_at_least(axes[1], series.get("crusher.zone_hardness_avg", []), 0.5)
    twins = []
    if "mill.hardness_avg" in series:
        twin = axes[3].twinx()
        twin.grid(False)
        hardness = series["mill.hardness_avg"].to_numpy()
        twin.plot(t, hardness, color="tab:red", lw=0.8,
                  label="mill hardness (30 s average, right axis)")
        twin.set_ylabel("mill hardness [-]", color="tab:red")
        twin.ticklabel_format(axis="y", useOffset=False)
        plotstyle.span_at_least(twin, hardness, 0.5)
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
