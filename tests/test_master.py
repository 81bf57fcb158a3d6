import numpy as np
import pytest

from cosim.errors import ValidationError
from cosim.master import Component, CosimulationError, Master


class Integrator(Component):
    input_names = ("rate",)

    def __init__(self, name):
        super().__init__()
        self.name = name
        self.level = 0.0

    def step(self, t, dt):
        self.level += self.inputs.get("rate", 0.0) * dt

    def outputs(self):
        return {"level": self.level, "profile": np.array([self.level, 2 * self.level])}


class Source(Component):
    name = "source"

    def step(self, t, dt):
        self.value = 1.0 if t >= 1.0 else 0.0

    def outputs(self):
        return {"rate": getattr(self, "value", 0.0)}


class Broken(Component):
    name = "broken"

    def step(self, t, dt):
        if t >= 2.0:
            raise RuntimeError("doStep returned fmi2Error")


def test_connect_run_and_record():
    master = Master(step=0.5, progress=False)
    source = master.add(Source())
    tank = master.add(Integrator("tank"))
    master.connect(source, "rate", tank, "rate")
    master.run(until=3.0)
    series = master.timeseries
    assert list(series.index) == [0.5, 1.0, 1.5, 2.0, 2.5, 3.0]
    # Gauss-Seidel: the tank sees the source's value of the same step
    assert series["tank.level"].tolist() == [0.0, 0.0, 0.5, 1.0, 1.5, 2.0]
    assert series["tank.profile[1]"].iloc[-1] == 4.0
    master.run(until=4.0)
    assert series.index[-1] < master.timeseries.index[-1] == 4.0


def test_a_failing_component_stops_the_run_and_keeps_the_data():
    master = Master(step=0.5, progress=False)
    master.add(Source())
    master.add(Broken())
    with pytest.raises(CosimulationError, match="broken failed at t = 2 s: doStep"):
        master.run(until=5.0)
    assert master.timeseries.index[-1] == 2.0


def test_bad_wiring_is_refused():
    master = Master(step=1.0, progress=False)
    source = master.add(Source())
    tank = master.add(Integrator("tank"))
    with pytest.raises(ValidationError, match="input"):
        master.connect(source, "rate", tank, "flow")
    with pytest.raises(ValidationError, match="name"):
        master.add(Integrator("tank"))
    master.connect(tank, "missing", tank, "rate")
    with pytest.raises(ValidationError, match="output"):
        master.run(until=1.0)
    with pytest.raises(ValidationError, match="step"):
        Master(step=0.0)
