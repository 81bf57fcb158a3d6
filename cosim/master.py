"""The co-simulation master: create components, connect signals, run.

Source: paper section "Digital twin as a distributed particle simulation"
(each asset a = operator u_a(t, dt) propagating its particles by one
propagation step dt; assets exchange signals and particles) and DESIGN.md
section 4 (the master steps all assets with a communication step, exchanges
signals and particles and records time series).

The API is deliberately small (after mosaik)::

    master = Master(step=0.5)
    crusher = master.add(CrusherAsset(...))         # any Component
    physics = master.add(FmuComponent(...))         # FMUs are Components too
    master.connect(crusher, "zone_hardness_mass", physics, "zone_hardness_mass")
    master.run(until=600.0)
    master.timeseries                               # pandas DataFrame

Components are stepped in the order they were added, each from t to t + dt.
Before a component steps, each of its connected inputs receives the
source's latest output: the value of the current step if the source was
added earlier (Gauss-Seidel order), else of the previous step. Particles
move between assets by changing their owner in the shared ``ParticleStore``
inside the assets' own ``step``; the master only moves signals.
"""

from __future__ import annotations

import time as wallclock
from dataclasses import dataclass

import numpy as np

from cosim.errors import ValidationError


class CosimulationError(RuntimeError):
    """A component failed during ``Master.run``; recorded data stays readable."""

    blames_component = True
    """The master names the component that was stepping; False for failures of a shared
    resource (the event store) that any component may hit first."""


class Component:
    """Base class of everything the master steps.

    Subclasses set ``name`` and override ``step``; ``outputs`` returns the
    signals to record and to pass on (floats or 1-D arrays); ``inputs``
    holds the values written by connections (and by the user through
    ``set_input``). ``finish`` releases resources at the end of a run.
    """

    name: str = "component"
    input_names: tuple[str, ...] = ()
    """Inputs this component accepts; ``connect`` refuses others (empty: any)."""

    def __init__(self):
        self.inputs: dict[str, object] = {}

    def set_input(self, name: str, value) -> None:
        if self.input_names and name not in self.input_names:
            raise ValidationError("input", f"one of {list(self.input_names)} of {self.name}",
                                  f"got {name!r}")
        self.inputs[name] = value

    def step(self, t: float, dt: float) -> None:
        raise NotImplementedError

    def outputs(self) -> dict[str, object]:
        return {}

    def finish(self) -> None:
        pass


@dataclass(frozen=True)
class Connection:
    source: Component
    output: str
    target: Component
    input: str


class Master:
    """Fixed-step co-simulation master.

    Parameters
    ----------
    step : float
        Communication step [s], default 0.5.
    record_every : int
        Record outputs every this many steps (default 1: every step).
    progress : bool or str
        Report progress on stderr during ``run`` (``cosim.progress``), default
        True; a string is the label of the progress lines (default "simulate").
    """

    def __init__(self, step: float = 0.5, *, record_every: int = 1,
                 progress: bool | str = True):
        if not (np.isfinite(step) and step > 0):
            raise ValidationError("step", "finite and > 0 s", f"got {step!r}")
        if int(record_every) < 1:
            raise ValidationError("record_every", ">= 1 step", f"got {record_every!r}")
        self.step = float(step)
        self.record_every = int(record_every)
        self.progress = progress
        self.time = 0.0
        self.components: list[Component] = []
        self.connections: list[Connection] = []
        self._by_target: dict[int, list[Connection]] = {}
        self._steps_done = 0
        self._records: list[dict[str, float]] = []
        self.wall_s = 0.0

    def add(self, component: Component) -> Component:
        """Add a component; names must be unique."""
        if any(c.name == component.name for c in self.components):
            raise ValidationError("name", "unique among the master's components",
                                  f"{component.name!r} exists")
        self.components.append(component)
        return component

    def connect(self, source: Component, output: str, target: Component, input: str) -> None:
        """Pass ``source``'s output ``output`` to ``target``'s input ``input`` every step."""
        for component in (source, target):
            if component not in self.components:
                raise ValidationError("component", "added to the master first",
                                      f"{component.name!r} is not")
        if target.input_names and input not in target.input_names:
            raise ValidationError("input", f"one of {list(target.input_names)} of {target.name}",
                                  f"got {input!r}")
        connection = Connection(source, output, target, input)
        self.connections.append(connection)
        self._by_target.setdefault(id(target), []).append(connection)

    def run(self, until: float) -> "Master":
        """Advance all components to time ``until`` [s] (continuing from ``self.time``)."""
        n_steps = int(round((until - self.time) / self.step))
        if n_steps < 0:
            raise ValidationError("until", f">= current time {self.time:g} s", f"got {until!r}")
        first = self._steps_done
        start = wallclock.perf_counter()
        report = None
        if self.progress:
            from cosim.progress import Progress

            report = Progress(self.progress if isinstance(self.progress, str) else "simulate",
                              until)
        latest = {id(c): c.outputs() for c in self.components}
        try:
            for k in range(first, first + n_steps):
                t = k * self.step
                for component in self.components:
                    for conn in self._by_target.get(id(component), ()):
                        value = latest[id(conn.source)].get(conn.output)
                        if value is None:
                            raise ValidationError(
                                "output", f"an output of {conn.source.name}",
                                f"{conn.output!r} not in {sorted(latest[id(conn.source)])}")
                        component.set_input(conn.input, value)
                    try:
                        component.step(t, self.step)
                    except Exception as exc:
                        if isinstance(exc, CosimulationError) and not exc.blames_component:
                            raise
                        raise CosimulationError(
                            f"{component.name} failed at t = {t:g} s: {exc}") from exc
                    latest[id(component)] = component.outputs()
                self._steps_done = k + 1
                self.time = self._steps_done * self.step
                if self._steps_done % self.record_every == 0:
                    self._record(latest)
                if report is not None:
                    report.update(self.time)
        finally:
            self.wall_s += wallclock.perf_counter() - start
            if report is not None:
                report.close()
        return self

    def finish(self) -> None:
        """Let every component release its resources (FMU instances, files)."""
        for component in self.components:
            component.finish()

    def _record(self, latest) -> None:
        row = {"time": self.time}
        for component in self.components:
            for signal, value in latest[id(component)].items():
                key = f"{component.name}.{signal}"
                if np.ndim(value) == 0:
                    row[key] = float(value)
                elif np.ndim(value) == 1:
                    for j, item in enumerate(np.asarray(value, dtype=float)):
                        row[f"{key}[{j}]"] = item
        self._records.append(row)

    @property
    def timeseries(self):
        """Recorded outputs as a DataFrame indexed by time [s]; columns ``component.signal``
        (1-D array outputs as ``component.signal[k]``)."""
        import pandas as pd

        frame = pd.DataFrame.from_records(self._records)
        return frame.set_index("time") if not frame.empty else frame
