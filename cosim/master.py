"""The co-simulation master: create components, connect signals, run.

Source: paper section "Digital twin as a distributed particle simulation"
(each asset a = operator u_a(t, dt) propagating its particles by one
propagation step dt; assets exchange signals and particles): the master
steps all assets with a communication step, exchanges signals and records
time series.

The API is deliberately small (after mosaik)::

    master = Master(step=0.5)
    crusher = master.add(CrusherAsset(...))         # any Component
    physics = master.add(FmuComponent(...))         # FMUs are Components too
    master.connect(crusher, "zone_hardness_mass", physics, "zone_hardness_mass")
    master.run(until=600.0)
    master.timeseries                               # pandas DataFrame

Particles are routed the same way, along flows::

    master.connect_flow(crusher, "product", belt, "feed")   # outlet -> inlet
    master.connect_flow(belt, "out", pile, "east", fraction=0.5)   # a split ...
    master.connect_flow(belt, "out", pile, "west", fraction=0.5)   # ... by mass

Components are stepped in the order they were added, each from t to t + dt.
Before a component steps, each of its connected inputs receives the
source's latest output: the value of the current step if the source was
added earlier (Gauss-Seidel order), else of the previous step. Particles
move between assets by changing their owner in the shared ``ParticleStore``;
an asset hands the particles leaving an outlet to the route the master
bound to it (``Component.routes``), inside its own ``step``, so material
handed downstream is processed there in the same step. Several flows into
one inlet merge; several flows out of one outlet split by mass.

Both ends are checked when they are wired (mosaik style: components
declare what they offer): ``connect`` refuses an output a component does
not declare in ``output_names`` and an input not in ``input_names``;
``connect_flow`` refuses an outlet not in ``outlets`` and an inlet not in
``inlets``. Nothing is checked per step.

A component may ask to end the simulation by setting ``stop_request`` to a
``StopRequest(time, reason)`` in its ``step`` (an FMU does when it requests
termination). The master finishes that communication step, records it at
the earliest requested time and ends the run; ``Master.stopped`` says which
component stopped it, when and why.

Recording writes into preallocated columns (grown by doubling): scalars of
each component's ``outputs()`` and 1-D arrays as ``signal[k]`` columns, of
the dtype the component declares in ``record_dtypes()`` (an FMU: its
variables' types) or float64.
"""

from __future__ import annotations

import functools
import math
import sys
import time as wallclock
from dataclasses import dataclass

import numba
import numpy as np

from cosim.errors import ValidationError, raise_if_interrupted


class CosimulationError(RuntimeError):
    """A component failed during ``Master.run``; recorded data stays readable."""

    blames_component = True
    """The master names the component that was stepping; False for failures of a shared
    resource (the event store) that any component may hit first."""


@dataclass(frozen=True)
class StopRequest:
    """A component's request to end the simulation at ``time`` [s], and why."""

    time: float
    reason: str


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
    stop_request: "StopRequest | None" = None
    """Set in ``step`` to end the simulation (the master reads it after each step)."""
    output_types: dict[str, str] = {}
    """FMI type name per output of a typed component (an FMU); empty: untyped floats."""
    output_names: tuple[str, ...] = ()
    """Outputs this component offers; ``connect`` refuses others (empty: any)."""
    inlets: tuple[str, ...] = ()
    """Where particles may enter (``connect_flow`` targets); empty: none."""
    outlets: tuple[str, ...] = ()
    """Where particles may leave (``connect_flow`` sources); empty: none."""
    limits_step: bool = False
    """Whether ``step_limit`` bounds an adaptive master's step (a component that
    implements it declares this True)."""

    def __init__(self):
        self.inputs: dict[str, object] = {}
        self.routes: dict[str, object] = {}
        """Outlet -> ``route(ids, t)`` that takes its particles; bound by
        ``Master.connect_flow`` (the target's ``receive`` for its inlet, or a ``Split``)."""

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

    def step_limit(self) -> float:
        """The largest communication step [s] that resolves this component's own
        dynamics in its present state (an adaptive master keeps its step within it
        when ``limits_step`` is declared; default: no limit)."""
        return np.inf

    def check_input_type(self, name: str, source_type: str, source: str) -> None:
        """Refuse a connection from an output of FMI type ``source_type`` that input
        ``name`` cannot take (a ``ValidationError``); untyped components take any."""

    def record_dtypes(self) -> dict:
        """numpy dtype per output signal for recording (missing: float64)."""
        return {}

    def receive(self, ids, t: float, inlet: str) -> None:
        """Take over particles ``ids`` at ``t`` through ``inlet`` (components with inlets)."""
        raise NotImplementedError

    def required_outlets(self) -> tuple[str, ...]:
        """Outlets particles will leave through: each must be routed before a run."""
        return self.outlets

    def send(self, outlet: str, ids, t: float) -> None:
        """Hand particles ``ids`` leaving through ``outlet`` at ``t`` to its route."""
        self.routes[outlet](ids, t)


@dataclass(frozen=True)
class Flow:
    """Particles leaving an outlet enter ``target`` through ``inlet``."""

    target: Component
    inlet: str
    fraction: float = 1.0

    def route(self):
        """The callable an outlet with this one flow hands its particles to."""
        return functools.partial(self.target.receive, inlet=self.inlet)


class Split:
    """An outlet feeding several flows: each gets its ``fraction`` of the mass.

    Particles leave whole, so the split is by a mass credit: each particle,
    in the order it leaves, goes to the flow furthest behind its share
    (sent_i - fraction_i * sent_total smallest; ties to the first flow).
    Over time every flow's mass is within one particle of its share.
    """

    def __init__(self, flows: list[Flow], masses):
        self.flows = list(flows)
        self.masses = masses          # ids -> masses [kg] (the shared particle store's)
        self.fractions = np.array([f.fraction for f in self.flows])
        self.sent = np.zeros(len(self.flows))

    def __call__(self, ids, t: float) -> None:
        if len(ids) == 0:
            return
        choice = _split_choice(self.masses(ids), self.fractions, self.sent)
        for k, flow in enumerate(self.flows):
            part = ids[choice == k]
            if part.size:
                flow.target.receive(part, t, flow.inlet)


@dataclass(frozen=True)
class Connection:
    source: Component
    output: str
    target: Component
    input: str


def ladder_exponent(limit: float, step: float) -> int | None:
    """k with ``limit == step * 2**k`` (to 1e-9 in k), or None when ``limit`` is not
    on the ladder of ``step``."""
    exponent = math.log2(limit / step)
    return int(round(exponent)) if abs(exponent - round(exponent)) <= 1e-9 else None


class AdaptiveStep:
    """Communication step control during a run, from the declared signals' zero-order-hold error.

    The master holds every signal constant over a communication step H (zero-order
    hold), so a signal y that changes over the step is passed on with the error of
    that hold: to first order |y(t + H) - y(t)| (Kübler and Schiehlen 2000; Arnold,
    Clauß and Schierz 2013, cited in ``cosim.analyses.coupling_step``). The estimate
    used here is the difference between the constant (held) and the linear
    extrapolation of the signal's history at the end of the next step, i.e. the
    comparison of two extrapolation polynomials of consecutive order of Schierz,
    Arnold and Clauß 2012 ("Co-simulation with communication step size control in
    an FMI compatible master algorithm", Proc. 9th Int. Modelica Conf., sec. 3):

        e = |y_n - y_(n-1)| / H_n * H / scale

    after the step H_n that ended at y_n, for the next step H, relative to the
    signal's scale (the largest |y| seen so far, at least ``scale_floor``); the
    largest over the declared signals is controlled. It needs no rollback: the
    particle assets share one particle store, draw from one random generator and
    write events, so a step cannot be repeated from a saved state (FMUs alone could:
    ours declare canGetAndSetFMUstate), and step doubling within the run is not
    possible; estimates from output history only are the methods for subsystems
    without rollback ("Error estimation and step size control with minimal
    subsystem interfaces", arXiv:2406.17353, 2024). A step whose estimate exceeds
    the tolerance is therefore not repeated: the next one is shortened.

    A signal shows the coupling error, not an asset's own discretization: an
    asset whose state needs a step no longer than some time scale says so in
    ``Component.step_limit`` (the jaw crusher: its zone's capacity over the jaw's
    throughput while it holds material, else its throughput is capped by the step),
    and the step stays within the smallest limit of the components.

    The step follows the elementary controller for an error proportional to H
    (Hairer, Nørsett and Wanner, "Solving ODEs I", sec. II.4):
    ``H_new = H * safety * tolerance / e``, limited to [H / 2^k, 2 H] per change,
    rounded down to the ladder ``step * 2^j`` within [``min_step``, ``max_step``],
    and grown only at a time that is a multiple of the larger step (the steps of a
    run then land on one grid and the recording times are hit exactly). The estimate
    is of the hold error over one step; a window mean's coupling error averages such
    errors and is then usually smaller, but this is not a proven bound: it is checked
    against a fine-step run (``tests/test_adaptive_step.py``, ``examples/
    adaptive_step.py``).

    Parameters
    ----------
    signals : list of str
        Declared signals ``component.output`` (``simulation.coupling_signals``).
    tolerance : float
        Largest relative coupling error [-] (``simulation.coupling_tolerance``), in (0, 1].
    min_step, max_step : float
        Limits of the step [s] (``simulation.step_min_s`` [0.125],
        ``simulation.step_max_s`` [2]); each the initial step times a power of two.
    safety : float
        Safety factor [-] on the tolerance, default 0.8 (Hairer et al.: 0.8-0.9).
    scale_floor : float
        Smallest scale of a signal [signal's unit], default 1e-9 (a signal at rest at 0).
    """

    def __init__(self, signals, tolerance: float, min_step: float, max_step: float, *,
                 safety: float = 0.8, scale_floor: float = 1e-9):
        if not signals:
            raise ValidationError("coupling_signals", "one or more component.output names "
                                  "for an adaptive step", "none declared")
        if not (np.isfinite(tolerance) and 0.0 < tolerance <= 1.0):
            raise ValidationError("coupling_tolerance", "in (0, 1] for an adaptive step",
                                  f"got {tolerance!r}")
        if not (np.isfinite(min_step) and np.isfinite(max_step) and 0 < min_step <= max_step):
            raise ValidationError("step_min_s", f"finite, > 0 and <= step_max_s {max_step!r} s",
                                  f"got {min_step!r}")
        if not 0.0 < safety <= 1.0:
            raise ValidationError("safety", "in (0, 1]", f"got {safety!r}")
        self.signals = [tuple(s.split(".", 1)) for s in signals]
        self.names = list(signals)
        self.tolerance = float(tolerance)
        self.min_step = float(min_step)
        self.max_step = float(max_step)
        self.safety = float(safety)
        self.scale_floor = float(scale_floor)

    def ladder(self, step: float) -> tuple[int, int]:
        """(exponent of ``min_step`` below ``step``, of ``max_step`` above it): both must
        be whole, i.e. the limits the initial step times powers of two."""
        exponents = []
        for field, limit in (("step_min_s", self.min_step), ("step_max_s", self.max_step)):
            exponent = ladder_exponent(limit, step)
            if exponent is None:
                raise ValidationError(field, f"step_s {step:g} s times a power of two "
                                      "(..., 1/4, 1/2, 1, 2, 4, ...)", f"got {limit:g} s")
            exponents.append(exponent)
        if not exponents[0] <= 0 <= exponents[1]:
            raise ValidationError("step_s", f"within [step_min_s {self.min_step:g}, "
                                  f"step_max_s {self.max_step:g}] s", f"got {step:g} s")
        return exponents[0], exponents[1]


class Master:
    """Co-simulation master with a fixed or an adaptive communication step.

    Parameters
    ----------
    step : float
        Communication step [s], default 0.5 (the initial step of an adaptive run).
    record_every : int
        Record outputs every this many steps (default 1: every step); an adaptive
        run records at every multiple of ``record_every * step`` seconds it reaches.
    progress : bool or str
        Report progress on stderr during ``run`` (``cosim.progress``), default
        True; a string is the label of the progress lines (default "simulate").
    adaptive : AdaptiveStep or None
        Adapt the step during the run (default None: the fixed ``step``); each change
        is logged in ``step_changes``.
    """

    def __init__(self, step: float = 0.5, *, record_every: int = 1,
                 progress: bool | str = True, adaptive: AdaptiveStep | None = None):
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
        self.flows: list[tuple[Component, str, Flow]] = []
        self._by_target: dict[int, list[Connection]] = {}
        self._steps_done = 0
        self._recorder = _Recorder()
        self.wall_s = 0.0
        self.stopped: dict | None = None
        """None, or {"component", "time", "reason"} of the stop request that ended the run."""
        self.adaptive = adaptive
        self.step_changes: list[dict] = []
        """Adaptive runs: {"time", "from_s", "to_s", "estimate", "signal"} per change."""
        if adaptive is not None:
            low, high = adaptive.ladder(self.step)
            self._levels = high - low              # steps min_step * 2^level, level 0..this
            self._level = -low                      # the initial step's
            self._ticks = 0                         # time in units of min_step
            self._record_interval = self.record_every * self.step
            self._next_record = self._record_interval
            self._step_sum = 0.0
            self._step_min = np.inf
            self._step_max = 0.0
            self._history = None                    # declared signals at the last point
            self._scale = None                      # their largest |value| so far

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
        if source.output_names and output not in source.output_names:
            raise ValidationError("output", f"one of {list(source.output_names)} of "
                                  f"{source.name}", f"got {output!r}")
        if target.input_names and input not in target.input_names:
            raise ValidationError("input", f"one of {list(target.input_names)} of {target.name}",
                                  f"got {input!r}")
        source_type = source.output_types.get(output)
        if source_type is not None:  # typed (FMU) signals: a mismatch is refused now
            target.check_input_type(input, source_type, f"{source.name}.{output}")
        connection = Connection(source, output, target, input)
        self.connections.append(connection)
        self._by_target.setdefault(id(target), []).append(connection)

    def connect_flow(self, source: Component, outlet: str, target: Component, inlet: str,
                     fraction: float = 1.0) -> None:
        """Route the particles leaving ``source`` through ``outlet`` into ``target``'s
        ``inlet``; a second flow from the same outlet makes a split by mass fractions
        (they must add up to 1 when the run starts)."""
        for component in (source, target):
            if component not in self.components:
                raise ValidationError("component", "added to the master first",
                                      f"{component.name!r} is not")
        for port, ports, owner, side in ((outlet, source.outlets, source, "outlet"),
                                         (inlet, target.inlets, target, "inlet")):
            if port not in ports:
                raise ValidationError(side, f"one of {list(ports)} of {owner.name}" if ports
                                      else f"absent: {owner.name} has no {side}",
                                      f"got {port!r}")
        if not (np.isfinite(fraction) and 0.0 < fraction <= 1.0):
            raise ValidationError("fraction", "in (0, 1]", f"got {fraction!r}")
        flow = Flow(target, inlet, float(fraction))
        self.flows.append((source, outlet, flow))
        routed = [f for s, o, f in self.flows if s is source and o == outlet]
        source.routes[outlet] = (flow.route() if len(routed) == 1
                                 else Split(routed, source.particle_masses))

    def check_flows(self) -> None:
        """Refuse a run with an outlet that is needed but not routed, or a split whose
        fractions do not add up to 1 (both named)."""
        for component in self.components:
            for outlet in component.required_outlets():
                if outlet not in component.routes:
                    raise ValidationError("flows", f"a flow from {component.name}.{outlet}",
                                          "the outlet is not connected")
            for outlet, route in component.routes.items():
                if isinstance(route, Split) and abs(route.fractions.sum() - 1.0) > 1e-9:
                    raise ValidationError(
                        "flows", f"fractions from {component.name}.{outlet} adding up to 1",
                        f"they add up to {route.fractions.sum():g}")

    def run(self, until: float) -> "Master":
        """Advance all components to time ``until`` [s] (continuing from ``self.time``);
        ends earlier if a component requests a stop (see ``stopped``)."""
        n_steps = int(round((until - self.time) / self.step))
        if n_steps < 0:
            raise ValidationError("until", f">= current time {self.time:g} s", f"got {until!r}")
        if self.stopped is not None and n_steps > 0:
            raise ValidationError("until", f"not past the stop requested by "
                                  f"{self.stopped['component']} at {self.stopped['time']:g} s",
                                  f"got {until!r}")
        if self._steps_done == 0:
            self.check_flows()
        first = self._steps_done
        start = wallclock.perf_counter()
        report = None
        if self.progress:
            from cosim.progress import Progress

            report = Progress(self.progress if isinstance(self.progress, str) else "simulate",
                              until)
        latest = {id(c): c.outputs() for c in self.components}
        inputs = [(c, [(conn.input, id(conn.source), conn.output, conn.source.name)
                       for conn in self._by_target.get(id(c), ())])
                  for c in self.components]
        record = self._recorder.record
        try:
            if self.adaptive is not None:
                self._run_adaptive(until, inputs, latest, report)
                return self
            for k in range(first, first + n_steps):
                t = k * self.step
                stops = self._advance(inputs, latest, t, self.step)
                self._steps_done = k + 1
                self.time = self._steps_done * self.step
                if stops:
                    self._stop(stops, t, latest)
                    break
                if self._steps_done % self.record_every == 0:
                    record(self.time, self.components, latest)
                if report is not None:
                    report.update(self.time)
        finally:
            self.wall_s += wallclock.perf_counter() - start
            if report is not None:
                report.close()
        return self

    def _advance(self, inputs, latest, t: float, dt: float):
        """Step every component from ``t`` to ``t + dt`` [s] in order, each after its
        inputs are set; the components that requested a stop (or None)."""
        stops = None
        for component, connections in inputs:
            for name, source, output, source_name in connections:
                try:
                    value = latest[source][output]
                except KeyError:
                    raise ValidationError(
                        "output", f"an output of {source_name}",
                        f"{output!r} not in {sorted(latest[source])}") from None
                component.set_input(name, value)
            try:
                component.step(t, dt)
            except Exception as exc:
                raise_if_interrupted(exc)
                if isinstance(exc, CosimulationError) and not exc.blames_component:
                    raise
                raise CosimulationError(
                    f"{component.name} failed at t = {t:g} s: {exc}") from exc
            latest[id(component)] = component.outputs()
            if component.stop_request is not None:
                stops = (stops or []) + [component]
        return stops

    def _run_adaptive(self, until: float, inputs, latest, report) -> None:
        """``run`` with the step of ``self.adaptive``: steps on the grid of its ladder
        (a step grows only at a multiple of the larger step; the last one fits
        ``until``), recorded at every multiple of the recording interval reached."""
        control = self.adaptive
        unit = control.min_step
        end = int(round(until / unit))
        by_name = {c.name: c for c in self.components}
        for name, (component, output) in zip(control.names, control.signals):
            if component not in by_name or output not in latest[id(by_name[component])]:
                raise ValidationError("coupling_signals", "outputs of the run's components "
                                      "(component.output)", f"{name!r} is not one")
        ends = [(id(by_name[c]), output) for c, output in control.signals]
        limited = [c for c in self.components if c.limits_step]
        if self._history is None:
            self._history = self._signals(latest, ends)
            self._scale = [max(abs(v), control.scale_floor) for v in self._history]
        record = self._recorder.record
        while self._ticks < end:
            size = 1 << self._level
            while self._ticks % size or self._ticks + size > end:
                size >>= 1
            t, dt = self._ticks * unit, size * unit
            stops = self._advance(inputs, latest, t, dt)
            self._ticks += size
            self._steps_done += 1
            self.time = self._ticks * unit
            self._step_sum += dt
            self._step_min = min(self._step_min, dt)
            self._step_max = max(self._step_max, dt)
            if stops:
                self._stop(stops, t, latest)
                break
            if self.time >= self._next_record - 1e-9 * unit:
                record(self.time, self.components, latest)
                self._next_record = (np.floor(self.time / self._record_interval + 1e-9) + 1) \
                    * self._record_interval
            self._control(self._signals(latest, ends), dt, limited)
            if report is not None:
                report.update(self.time)

    @staticmethod
    def _signals(latest, ends) -> list[float]:
        """The declared signals' values (not finite: 0); plain floats, as the control
        runs every step on a few values."""
        values = [float(latest[component][output]) for component, output in ends]
        return [v if math.isfinite(v) else 0.0 for v in values]

    def _control(self, values: list[float], dt: float, limited) -> None:
        """Choose the next step from the change of the declared signals over the step
        ``dt`` [s] just taken and the ``step_limit`` of the components in ``limited``
        (``AdaptiveStep``); log a change."""
        control = self.adaptive
        scale = self._scale = [max(s, abs(v)) for s, v in zip(self._scale, values)]
        change = [abs(v - h) / s for v, h, s in zip(values, self._history, scale)]  # [-]
        self._history = values
        worst = max(range(len(change)), key=change.__getitem__)
        rate = change[worst] / dt                        # [1/s]
        level = self._level + 1
        if rate > 0:
            wanted = control.safety * control.tolerance / rate / control.min_step
            level = math.floor(math.log2(wanted)) if wanted >= 1.0 else 0
        if limited:
            limit = min(component.step_limit() for component in limited)
            if limit < math.inf:
                level = min(level, math.floor(math.log2(limit / control.min_step))
                            if limit >= control.min_step else 0)
        level = max(0, min(level, self._level + 1, self._levels))
        if level != self._level:
            self.step_changes.append({
                "time": self.time, "from_s": control.min_step * (1 << self._level),
                "to_s": control.min_step * (1 << level), "estimate": change[worst],
                "signal": control.names[worst]})
            self._level = level

    def step_statistics(self) -> dict:
        """The communication steps of the run so far: mode, count, min, max, mean [s];
        an adaptive run adds its tolerance, signals, limits and number of changes."""
        if self.adaptive is None:
            return {"mode": "fixed", "count": self._steps_done, "min_s": self.step,
                    "max_s": self.step, "mean_s": self.step}
        control = self.adaptive
        count = self._steps_done
        return {"mode": "adaptive", "count": count,
                "min_s": float(self._step_min) if count else None,
                "max_s": float(self._step_max) if count else None,
                "mean_s": self._step_sum / count if count else None,
                "tolerance": control.tolerance, "signals": control.names,
                "step_min_s": control.min_step, "step_max_s": control.max_step,
                "safety": control.safety, "changes": len(self.step_changes)}

    def _stop(self, components, t: float, latest) -> None:
        """End the run at the earliest requested stop time within the step [t, t + step]."""
        first = min(components, key=lambda c: c.stop_request.time)
        request = first.stop_request
        when = min(max(request.time, t), self.time)
        self.stopped = {"component": first.name, "time": when, "reason": request.reason}
        self.time = when
        recorder = self._recorder
        if recorder.rows == 0 or recorder.time[recorder.rows - 1] != when:
            recorder.record(when, self.components, latest)
        if self.progress:
            print(f"\nstopped at t = {when:g} s by {first.name}: {request.reason}",
                  file=sys.stderr)

    def finish(self) -> None:
        """Let every component release its resources (FMU instances, files)."""
        for component in self.components:
            component.finish()

    @property
    def timeseries(self):
        """Recorded outputs as a DataFrame indexed by time [s]; columns ``component.signal``
        (1-D array outputs as ``component.signal[k]``)."""
        return self._recorder.frame()


@numba.njit(cache=True)
def _split_choice(masses, fractions, sent):
    """Flow index per particle for ``Split`` (updates ``sent`` [kg] in place)."""
    choice = np.empty(masses.size, dtype=np.int64)
    for i in range(masses.size):
        total = sent.sum()
        best, lag = 0, np.inf
        for k in range(fractions.size):
            behind = sent[k] - fractions[k] * total
            if behind < lag:
                best, lag = k, behind
        choice[i] = best
        sent[best] += masses[i]
    return choice


def _missing(dtype):
    """Value of a recorded column where its signal is absent."""
    return np.nan if dtype.kind in "fc" else (None if dtype.kind == "O" else 0)


class _Recorder:
    """Time series in preallocated numpy columns, one block per (component, signal).

    The layout of a component is fixed on its first record; a record whose
    outputs differ in keys or shapes adds columns (earlier rows: NaN for
    float columns)."""

    def __init__(self):
        self.rows = 0
        self.capacity = 0
        self.time = np.empty(0)
        # id(component) -> (n_keys, [(signal, block)], [(signal, block, width)])
        self.layouts: dict[int, tuple] = {}
        self.blocks: dict[str, np.ndarray] = {}  # "component.signal" -> (capacity[, n])
        self.order: list[str] = []

    def record(self, time: float, components, latest) -> None:
        row = self.rows
        if row == self.capacity:
            self._grow()
        self.time[row] = time
        for component in components:
            outputs = latest[id(component)]
            layout = self.layouts.get(id(component))
            if layout is None or layout[0] != len(outputs):
                layout = self._layout(component, outputs)
            try:
                for signal, block in layout[1]:
                    block[row] = outputs[signal]
                for signal, block, width in layout[2]:
                    value = outputs[signal]
                    if len(value) != width:  # numpy would broadcast a length-1 array
                        raise ValueError(signal)
                    block[row] = value
            except (KeyError, ValueError, TypeError):  # keys or lengths changed: the slow way
                layout = self._layout(component, outputs)
                for signal, block, *_ in layout[1] + layout[2]:
                    value = outputs[signal]
                    if block.ndim == 2:
                        block[row] = _missing(block.dtype)
                        value = np.atleast_1d(value)
                        block[row, :len(value)] = value
                    else:
                        block[row] = value
        self.rows = row + 1

    def _layout(self, component, outputs) -> tuple:
        dtypes = component.record_dtypes()
        scalars, arrays = [], []
        for signal, value in outputs.items():
            ndim = np.ndim(value)
            if ndim > 1:
                continue
            key = f"{component.name}.{signal}"
            dtype = np.dtype(dtypes.get(signal, np.float64))
            width = () if ndim == 0 else (len(value),)
            block = self.blocks.get(key)
            if block is None:
                block = self._new_block(dtype, width)
                self.order.append(key)
                self.blocks[key] = block
            elif block.shape[1:] != width and (block.ndim == 1 or width == ()
                                               or width[0] > block.shape[1]):
                # a scalar became an array (or the reverse), or an array grew: widen
                widest = (max(block.shape[1] if block.ndim == 2 else 1,
                              width[0] if width else 1),)
                grown = self._new_block(np.result_type(block.dtype, dtype), widest)
                grown[:self.rows, :(block.shape[1] if block.ndim == 2 else 1)] = \
                    block[:self.rows].reshape(self.rows, -1)
                self.blocks[key] = block = grown
            if block.ndim == 1:
                scalars.append((signal, block))
            else:
                arrays.append((signal, block, block.shape[1]))
        layout = (len(outputs), scalars, arrays)
        self.layouts[id(component)] = layout
        return layout

    def _new_block(self, dtype, width) -> np.ndarray:
        block = np.empty((self.capacity, *width), dtype=dtype)
        block[:] = _missing(dtype)
        return block

    def _grow(self) -> None:
        capacity = max(64, 2 * self.capacity)
        self.time = np.resize(self.time, capacity)
        renamed = {}
        for key, block in self.blocks.items():
            grown = np.empty((capacity, *block.shape[1:]), dtype=block.dtype)
            grown[:self.capacity] = block
            grown[self.capacity:] = _missing(block.dtype)  # rows a signal is absent from
            renamed[id(block)] = grown
            self.blocks[key] = grown
        self.capacity = capacity
        self.layouts = {cid: (n, [(signal, renamed[id(block)]) for signal, block in scalars],
                              [(signal, renamed[id(block)], width)
                               for signal, block, width in arrays])
                        for cid, (n, scalars, arrays) in self.layouts.items()}

    def frame(self):
        import pandas as pd

        if self.rows == 0:
            return pd.DataFrame()
        columns = {}
        for key in self.order:
            block = self.blocks[key][:self.rows]
            if block.ndim == 1:
                columns[key] = block.copy()
            else:
                for j in range(block.shape[1]):
                    columns[f"{key}[{j}]"] = block[:, j].copy()
        frame = pd.DataFrame(columns, index=pd.Index(self.time[:self.rows].copy(), name="time"))
        return frame
