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


class SignalledKernel(Component):
    """Fails from ``t_s`` on as a numba kernel does when a signal whose handler raises
    ``cause`` (SIGINT: KeyboardInterrupt; a SIGTERM handler's sys.exit: SystemExit)
    lands while it boxes its result."""

    name = "kernel"

    def __init__(self, cause, t_s=0.0):
        super().__init__()
        self.cause, self.t_s = cause, t_s

    def step(self, t, dt):
        if t >= self.t_s:
            raise SystemError("CPUDispatcher(<function _slot_sums>) returned a result with an "
                              "exception set") from self.cause


def test_ctrl_c_inside_a_numba_kernel_stops_the_run_instead_of_failing_the_component():
    master = Master(step=0.5, progress=False)
    master.add(Source())
    master.add(SignalledKernel(KeyboardInterrupt(), t_s=1.5))
    with pytest.raises(KeyboardInterrupt) as raised:
        master.run(until=5.0)
    assert isinstance(raised.value.__cause__, SystemError)
    assert master.timeseries.index[-1] == 1.5  # as a failing component keeps its data


def test_a_stopping_signal_inside_a_numba_kernel_exits_as_its_handler_asked():
    master = Master(step=0.5, progress=False)
    master.add(SignalledKernel(SystemExit(0)))
    with pytest.raises(SystemExit) as raised:
        master.run(until=5.0)
    assert raised.value.code == 0


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


# ---------------------------------------------------------------- flows of particles
from cosim.assets import Asset, Plant, PlantBalance  # noqa: E402
from cosim.particles import ParticleStore  # noqa: E402


class Feeder(Asset):
    """Puts one 10 kg particle per step onto its outlet."""

    inlets = ()
    output_names = ("fed_kg",)

    def step(self, t, dt):
        ids = self.particles.add(mass=np.full(1, 10.0), f=np.full((1, 16), 1 / 16), grade=0.5,
                                 hardness=1.0, position=self.location, owner=self.owner, time=t)
        self.plant.mass_in += 10.0
        self.send("out", ids, t + dt)

    def outputs(self):
        return {"fed_kg": self.plant.mass_in}


class Bin(Asset):
    """Holds what it receives; counts by inlet."""

    inlets = ("top", "side")
    outlets = ()

    def __init__(self, name, plant):
        super().__init__(name, plant)
        self.by_inlet = {"top": 0, "side": 0}

    def _accept(self, ids, t, inlet):
        self.by_inlet[inlet] += ids.size

    def step(self, t, dt):
        pass


def _plant():
    plant = Plant(ParticleStore(capacity=64))
    master = Master(step=1.0, progress=False)
    return plant, master


def test_flows_route_particles_split_by_mass_and_merge():
    plant, master = _plant()
    feeders = [master.add(Feeder(f"feeder_{k}", plant)) for k in range(2)]
    bin_ = master.add(Bin("bin", plant))
    master.add(PlantBalance(plant))
    master.connect_flow(feeders[0], "out", bin_, "top", fraction=0.25)
    master.connect_flow(feeders[0], "out", bin_, "side", fraction=0.75)
    master.connect_flow(feeders[1], "out", bin_, "side")          # merges into "side"
    master.run(8.0)
    assert bin_.by_inlet == {"top": 2, "side": 6 + 8}             # 1 in 4 of feeder_0's
    assert plant.particles.total_mass(bin_.owner) == pytest.approx(160.0)
    assert master.timeseries["plant.mass_balance_rel_error"].max() == 0.0


def test_both_ends_of_a_flow_and_of_a_signal_are_checked_when_wired():
    plant, master = _plant()
    feeder, bin_ = master.add(Feeder("feeder", plant)), master.add(Bin("bin", plant))
    with pytest.raises(ValidationError, match=r"outlet: must be one of \['out'\] of feeder"):
        master.connect_flow(feeder, "spout", bin_, "top")
    with pytest.raises(ValidationError, match=r"inlet: must be one of \['top', 'side'\] of bin"):
        master.connect_flow(feeder, "out", bin_, "bottom")
    with pytest.raises(ValidationError, match=r"outlet: must be absent: bin has no outlet"):
        master.connect_flow(bin_, "out", feeder, "feed")
    with pytest.raises(ValidationError, match=r"inlet: must be absent: feeder has no inlet"):
        master.connect_flow(feeder, "out", feeder, "feed")
    with pytest.raises(ValidationError, match=r"output: must be one of \['fed_kg'\] of feeder"):
        master.connect(feeder, "fed", bin_, "rate")


def test_a_run_refuses_an_unrouted_outlet_and_fractions_not_adding_up_to_one():
    plant, master = _plant()
    feeder, bin_ = master.add(Feeder("feeder", plant)), master.add(Bin("bin", plant))
    with pytest.raises(ValidationError, match="a flow from feeder.out"):
        master.run(1.0)
    master.connect_flow(feeder, "out", bin_, "top", fraction=0.5)
    master.connect_flow(feeder, "out", bin_, "side", fraction=0.25)
    with pytest.raises(ValidationError, match="fractions from feeder.out adding up to 1"):
        master.run(1.0)


def test_connect_refuses_an_output_the_fmu_does_not_declare():
    from cosim.fmu import CRUSHER_INTERFACE, FmuComponent, fmu_path

    master = Master(step=0.5, progress=False)
    crusher = master.add(FmuComponent(fmu_path("crusher"), interface=CRUSHER_INTERFACE))
    level = master.add(Integrator("level"))
    try:
        with pytest.raises(ValidationError, match=r"output: must be one of \[.*'power'.*\] of "
                                                  r"crusher \(got 'powr'\)"):
            master.connect(crusher, "powr", level, "rate")
        master.connect(crusher, "power", level, "rate")
    finally:
        master.finish()
