"""Run a mine-simulator scenario for a test: overrides, seed, results in one object.

Wraps ``cosim.scenario`` (load, validate, build, run, write): the scenario
TOML is read, dotted ``overrides`` are applied (``{"assets.crusher.fmu":
"cone_crusher", "assets.stockpile.model": "mixing"}``), the result is validated by
the simulator's own rules (so a typo in an override is an error naming the
key) and run into ``out``, which then holds ``timeseries.parquet``,
``events.sqlite`` and ``summary.json`` as ``minetwin simulate`` writes them.
The ``[reference]`` table (``minetwin.testing.reference``) is not the
simulator's and is set aside before validation.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

from cosim.errors import ValidationError
from cosim.tomlfile import read_toml


@dataclass
class ScenarioRun:
    """A finished scenario run.

    Attributes
    ----------
    timeseries : pandas.DataFrame
        Every recorded signal, indexed by time [s] (columns ``component.signal``).
    events : cosim.events.EventStore
        The macro-tracking events (open for reading; closed by ``close``).
    summary : dict
        ``summary.json`` (mass in/held/out, particles, timing, signal means).
    out : Path
        The folder holding the run's files.
    config : dict
        The validated scenario that ran (after overrides).
    simulation : cosim.scenario.Simulation
        The built plant after the run (assets, particle store, master).
    """

    timeseries: object
    events: object
    summary: dict
    out: Path
    config: dict
    simulation: object = field(repr=False, default=None)

    def close(self) -> None:
        if self.events is not None:
            self.events.close()

    def assert_mass_balance(self, rtol: float = 1e-9) -> float:
        """Plant-wide: mass in = mass held + mass out at the end (``summary.json``),
        and at every recorded time (``plant.mass_balance_rel_error`` if recorded)."""
        __tracebackhide__ = True
        from minetwin.testing.assertions import assert_mass_balance

        worst = assert_mass_balance(self.summary, rtol=rtol, where="the plant")
        column = "plant.mass_balance_rel_error"
        if column in self.timeseries:
            errors = self.timeseries[column].to_numpy()
            bad = ~(errors <= rtol)
            if bad.any():
                i = int(bad.argmax())
                raise AssertionError(
                    f"mass balance of the plant broken at t = {self.timeseries.index[i]:g} s: "
                    f"relative error {errors[i]:.3g} > rtol {rtol:g} (column {column}); "
                    f"{int(bad.sum())} recorded time(s) affected")
            worst = max(worst, float(errors.max()))
        return worst

    def assert_particle_ids_accounted(self):
        """Every particle that appeared (event store) is in the plant or has left it, once."""
        __tracebackhide__ = True
        from minetwin.testing.assertions import assert_ids_accounted

        appeared = self.events.particles(type="appear")["particle_id"].to_numpy()
        plant = self.simulation.plant
        return assert_ids_accounted(appeared, held=plant.particles.id, left=plant.removed_ids,
                                    kind="particle id", where="the plant")


def apply_overrides(document: dict, overrides: dict | None) -> dict:
    """A copy of ``document`` with dotted keys set (``"assets.stockpile.model": "mixing"``).

    Every table on the way must exist; the last key may be new (optional
    keys); the simulator's validation then refuses unknown ones.
    """
    result = copy.deepcopy(document)
    for dotted, value in (overrides or {}).items():
        parts = str(dotted).split(".")
        table = result
        for depth, part in enumerate(parts[:-1]):
            if not isinstance(table.get(part), dict):
                where = ".".join(parts[:depth + 1])
                raise ValidationError(f"overrides[{dotted!r}]", "a key inside existing tables",
                                      f"the scenario has no table {where!r}; tables there: "
                                      f"{sorted(k for k, v in table.items() if isinstance(v, dict))}")
            table = table[part]
        table[parts[-1]] = value
    return result


def read_document(path) -> dict:
    return read_toml(path, "scenario")


def run_scenario(path, *, until: float | None = None, overrides: dict | None = None,
                 seed: int | None = None, out=None, storage_model: str | None = None,
                 progress: bool = False) -> ScenarioRun:
    """Run scenario TOML ``path`` to ``until`` [s] (default: the scenario's) into ``out``.

    ``seed`` overrides the scenario's seed; ``storage_model`` its stockpile
    model. Returns a ``ScenarioRun`` (call ``close()`` when done, or use the
    pytest fixture, which does).
    """
    import tempfile

    import pandas as pd

    from cosim import scenario
    from cosim.events import EventStore

    document = read_document(path)
    document.pop("reference", None)
    config = scenario.validate(apply_overrides(document, overrides))
    out = Path(out) if out is not None else Path(tempfile.mkdtemp(prefix="minetwin-run-"))
    simulation, summary = scenario.run_scenario(config, out, until=until, seed=seed,
                                                storage_model=storage_model, progress=progress)
    timeseries = pd.read_parquet(out / "timeseries.parquet")
    events = EventStore(out / "events.sqlite")
    return ScenarioRun(timeseries=timeseries, events=events, summary=summary, out=out,
                       config=config, simulation=simulation)
