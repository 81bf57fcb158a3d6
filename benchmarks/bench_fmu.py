"""FMU benchmarks (issue 3): master cost per FMU step against the bare fmpy call
on the same FMU, and the mill operator's cost per particle-step.

* bare fmpy: per step, set all inputs, ``doStep``, get all outputs through
  fmpy's FMU slave methods (``setFloat64``/``doStep``/``getFloat64`` for FMI
  3.0, ``setReal``/``doStep``/``getReal`` for FMI 2.0), value references
  prepared once.
* component: ``FmuComponent.set_input`` for each input + ``step`` (returns
  the outputs as numpy arrays).
* master: ``Master.run`` with the FMU's inputs fed by a connected component,
  recording every output each step.
Target: master overhead at most 2x the bare call (process CPU time, best of
3, both sides measured the same way; wall times are reported too). Mill operator (``mill_step_mass``, default
exponential integrator): < 1 us per particle-step of CPU time (wall time also
reported).

Prints one JSON object (progress on stderr):

    .venv/bin/python benchmarks/bench_fmu.py [--steps 5000] [--particles 20000]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from cosim import jsonio, sizes
from cosim.comminution import mill_step_mass
from cosim.fmu import CRUSHER_INTERFACE, MILL_INTERFACE, FmuComponent, fmu_path
from cosim.master import Component, Master


def cpu_best_of(repeats, fn):
    """Best (wall, process CPU) times [s]; CPU time is what the code costs on a busy machine."""
    runs = [_timed(fn) for _ in range(repeats)]
    return min(r[0] for r in runs), min(r[1] for r in runs)


def _timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - wall, time.process_time() - cpu


class Feed(Component):
    """Constant inputs for the FMU under test (the master passes them each step)."""

    def __init__(self, values: dict):
        super().__init__()
        self.name = "feed"
        self.values = values

    def step(self, t, dt):
        pass

    def outputs(self):
        return self.values


def _inputs(model):
    if model.startswith("crusher"):
        return {"speed": 10.0, "zone_hardness_mass": np.linspace(10.0, 100.0, 16)}
    return {"speed_setpoint": 1.2, "charge_mass": np.full(16, 100.0)}


def bench_bare_fmpy(path, inputs: dict, steps: int, dt: float = 0.5) -> float:
    """Seconds per step of set inputs + doStep + get outputs through fmpy's slave methods."""
    import shutil

    from fmpy import extract, read_model_description
    from fmpy.fmi2 import FMU2Slave
    from fmpy.fmi3 import FMU3Slave

    md = read_model_description(str(path))
    unzipdir = extract(str(path))
    fmi3 = md.fmiVersion == "3.0"
    cls = FMU3Slave if fmi3 else FMU2Slave
    slave = cls(guid=md.guid, unzipDirectory=unzipdir,
                modelIdentifier=md.coSimulation.modelIdentifier, instanceName="bare")
    slave.instantiate()
    if not fmi3:
        slave.setupExperiment(startTime=0.0)
    slave.enterInitializationMode()
    slave.exitInitializationMode()
    by_name = {v.name: v for v in md.modelVariables}
    in_refs, in_values = [], []
    for name, value in inputs.items():
        if fmi3 or np.ndim(value) == 0:
            in_refs.append(by_name[name].valueReference)
        else:
            in_refs += [by_name[f"{name}[{i + 1}]"].valueReference for i in range(len(value))]
        in_values += list(np.atleast_1d(value).astype(float))
    outputs = [v for v in md.modelVariables if v.causality == "output"]
    out_refs = [v.valueReference for v in outputs]
    n_out = sum(int(np.prod(v.shape or ())) if fmi3 else 1 for v in outputs)
    set_values = slave.setFloat64 if fmi3 else slave.setReal
    get_values = (lambda refs: slave.getFloat64(refs, n_out)) if fmi3 else slave.getReal

    def run():
        t = 0.0
        for _ in range(steps):
            set_values(in_refs, in_values)
            slave.doStep(t, dt)
            get_values(out_refs)
            t += dt

    try:
        return tuple(x / steps for x in cpu_best_of(3, run))
    finally:
        slave.terminate()
        slave.freeInstance()
        shutil.rmtree(unzipdir, ignore_errors=True)


def bench_component(path, interface, inputs: dict, steps: int, dt: float = 0.5) -> float:
    component = FmuComponent(path, interface=interface)

    def run():
        t = 0.0
        for _ in range(steps):
            for name, value in inputs.items():
                component.set_input(name, value)
            component.step(t, dt)
            component.outputs()
            t += dt

    try:
        return tuple(x / steps for x in cpu_best_of(3, run))
    finally:
        component.finish()


def bench_master(path, interface, inputs: dict, steps: int, dt: float = 0.5) -> float:
    def run():
        master = Master(step=dt, progress=False)
        feed = master.add(Feed(inputs))
        fmu = master.add(FmuComponent(path, interface=interface, name="fmu"))
        for name in inputs:
            master.connect(feed, name, fmu, name)
        elapsed = _timed(lambda: master.run(steps * dt))
        master.finish()
        return elapsed

    runs = [run() for _ in range(3)]
    return min(r[0] for r in runs) / steps, min(r[1] for r in runs) / steps


def bench_mill_operator(particles: int, steps: int = 20) -> dict:
    rng = np.random.default_rng(0)
    class_mass = 100.0 * sizes.blasted_fractions(rng, particles)
    hardness = rng.uniform(1.0, 2.0, particles)
    mill = FmuComponent(fmu_path("mill"), interface=MILL_INTERFACE)
    mill.set_input("charge_mass", class_mass.sum(axis=0))
    mill.step(0.0, 0.5)
    ops = mill.outputs()
    mill.finish()
    args = (hardness, ops["breakage_rate"], ops["daughter_fraction"], ops["escape_rate"], 0.5)
    mill_step_mass(class_mass[:10], hardness[:10], *args[1:])  # compile
    result = {}
    for method in ("exponential", "explicit"):
        def run():
            x = class_mass
            for _ in range(steps):
                x, _ = mill_step_mass(x, *args, method=method)

        wall, cpu = cpu_best_of(5, run)
        result[f"{method}_us_per_particle_step"] = cpu / (steps * particles) * 1e6
        result[f"{method}_wall_us_per_particle_step"] = wall / (steps * particles) * 1e6
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=5000, help="FMU steps per timing (5000)")
    parser.add_argument("--particles", type=int, default=20000,
                        help="particles in the mill operator timing (20000, the paper's pile)")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.particles < 1:
        print("bench_fmu: error: --steps and --particles must be >= 1", file=sys.stderr)
        return 2
    result = {"fmu": {}, "note": "us_per_step figures are process CPU time per communication "
                                 "step (best of 3); wall_us_per_step is inflated when other "
                                 "processes share the cores"}
    for model, interface in (("crusher", CRUSHER_INTERFACE), ("mill", MILL_INTERFACE)):
        for fmi in (3, 2):
            path = fmu_path(model, fmi)
            inputs = _inputs(model)
            print(f"timing {path.name} ...", file=sys.stderr)
            bare = bench_bare_fmpy(path, inputs, args.steps)
            component = bench_component(path, interface, inputs, args.steps)
            master = bench_master(path, interface, inputs, args.steps)
            result["fmu"][path.name] = {
                "bare_fmpy_us_per_step": bare[1] * 1e6,
                "component_us_per_step": component[1] * 1e6,
                "master_us_per_step": master[1] * 1e6,
                "master_over_bare": master[1] / bare[1],
                "wall_us_per_step": {"bare_fmpy": bare[0] * 1e6, "component": component[0] * 1e6,
                                     "master": master[0] * 1e6},
                "target_master_over_bare": 2.0,
                "meets_target": master[1] / bare[1] <= 2.0,
            }
    print("timing mill operator ...", file=sys.stderr)
    operator = bench_mill_operator(args.particles)
    operator["particles"] = args.particles
    operator["target_us_per_particle_step"] = 1.0
    operator["meets_target"] = operator["exponential_us_per_particle_step"] < 1.0
    operator["note"] = ("us_per_particle_step is process CPU time (best of 5); wall time is "
                        "also given and is inflated when other processes share the cores")
    result["mill_operator"] = operator
    print(jsonio.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
