"""FMU benchmarks (issues 3, 19): the master's cost per FMU step against the bare
fmpy calls on the same FMU, and the mill operator's cost per particle-step.

* bare fmpy: per step, set every input, ``doStep``, get every output through
  fmpy's FMU slave methods (``setFloat64``/``doStep``/``getFloat64`` and the
  other types' methods for FMI 3.0, ``setReal``/``setInteger``/``doStep``/
  ``getReal``/``getInteger`` for FMI 2.0), value references prepared once.
* component: ``FmuComponent.set_input`` for each input + ``step`` +
  ``outputs`` (typed values, arrays as numpy arrays).
* master: ``Master.run`` with the FMU's inputs fed by a connected component,
  recording every output each step.

The three are timed alternately, ``--rounds`` times in one process (so load
from other processes hits all of them alike); the figure is the median over
the rounds of each one's process CPU time per step, and the ratios are of
those medians (each round's ratio range is reported too, with the load
average). Targets: master / bare <= 1.5, component / bare <= 1.2. FMUs: the
crusher and mill (FMI 3 and 2) and the test stair counter (a small FMU with
an Int32 input and Int32 + Float64 outputs, where per-step overhead weighs
most). Mill operator (``mill_step_mass``, default exponential integrator):
< 1 us per particle-step of CPU time.

Prints one JSON object (progress on stderr):

    .venv/bin/python benchmarks/bench_fmu.py [--steps 5000] [--rounds 7] [--particles 20000]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import time

import numpy as np

from cosim import jsonio, sizes
from cosim.comminution import mill_step_mass
from cosim.fmu import CRUSHER_INTERFACE, MILL_INTERFACE, FmuComponent, fmu_path
from cosim.master import Component, Master

TARGET_MASTER = 1.5
TARGET_COMPONENT = 1.2


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


def _cases():
    from fmus.typed import typed_fmu_file

    for fmi in (3, 2):
        yield (fmu_path("crusher", fmi), CRUSHER_INTERFACE,
               {"speed": 10.0, "zone_hardness_mass": np.linspace(10.0, 100.0, 16)}, {})
        yield (fmu_path("mill", fmi), MILL_INTERFACE,
               {"speed_setpoint": 1.2, "charge_mass": np.full(16, 100.0)}, {})
        yield (typed_fmu_file("counter", fmi), (), {"increment": 2}, {"stop_time": 1e9})


class BareFmpy:
    """The FMU through fmpy's slave methods only."""

    def __init__(self, path, inputs: dict, parameters: dict):
        from fmpy import extract, read_model_description
        from fmpy.fmi2 import FMU2Slave
        from fmpy.fmi3 import FMU3Slave

        md = read_model_description(str(path))
        self.unzipdir = extract(str(path))
        fmi3 = md.fmiVersion == "3.0"
        cls = FMU3Slave if fmi3 else FMU2Slave
        slave = cls(guid=md.guid, unzipDirectory=self.unzipdir,
                    modelIdentifier=md.coSimulation.modelIdentifier, instanceName="bare")
        slave.instantiate()
        if not fmi3:
            slave.setupExperiment(startTime=0.0)
        slave.enterInitializationMode()
        by_name = {v.name: v for v in md.modelVariables}
        for name, value in parameters.items():
            setter = "setFloat64" if fmi3 else "setReal"
            getattr(slave, setter)([by_name[name].valueReference], [value])
        slave.exitInitializationMode()
        method = {"Real": "Real", "Integer": "Integer", "Float64": "Float64", "Int32": "Int32"}
        self.sets = {}
        for name, value in inputs.items():
            if fmi3 or np.ndim(value) == 0:
                variable = by_name[name]
                refs = [variable.valueReference]
            else:
                variable = by_name[f"{name}[1]"]
                refs = [by_name[f"{name}[{i + 1}]"].valueReference for i in range(len(value))]
            kind = method[variable.type]
            entry = self.sets.setdefault(kind, ([], []))
            entry[0].extend(refs)
            entry[1].extend(np.atleast_1d(value).tolist())
        self.gets = {}
        for v in md.modelVariables:
            if v.causality == "output":
                entry = self.gets.setdefault(method[v.type], [[], 0])
                entry[0].append(v.valueReference)
                entry[1] += int(np.prod(v.shape or ())) if fmi3 else 1
        self.set_calls = [(getattr(slave, f"set{kind}"), refs, values)
                          for kind, (refs, values) in self.sets.items()]
        self.get_calls = [((lambda f, r, n: lambda: f(r, n))(getattr(slave, f"get{kind}"), refs, n)
                           if fmi3 else (lambda f, r: lambda: f(r))(getattr(slave, f"get{kind}"),
                                                                     refs))
                          for kind, (refs, n) in self.gets.items()]
        self.slave = slave
        self.t = 0.0

    def run(self, steps: int, dt: float) -> None:
        slave, set_calls, get_calls = self.slave, self.set_calls, self.get_calls
        t = self.t
        for _ in range(steps):
            for setter, refs, values in set_calls:
                setter(refs, values)
            slave.doStep(t, dt)
            for getter in get_calls:
                getter()
            t += dt
        self.t = t

    def close(self) -> None:
        self.slave.terminate()
        self.slave.freeInstance()
        shutil.rmtree(self.unzipdir, ignore_errors=True)


class ComponentOnly:
    def __init__(self, path, interface, inputs, parameters):
        self.component = FmuComponent(path, interface=interface, parameters=parameters)
        self.inputs = list(inputs.items())
        self.t = 0.0

    def run(self, steps, dt):
        component, inputs, t = self.component, self.inputs, self.t
        for _ in range(steps):
            for name, value in inputs:
                component.set_input(name, value)
            component.step(t, dt)
            component.outputs()
            t += dt
        self.t = t

    def close(self):
        self.component.finish()


class MasterRun:
    def __init__(self, path, interface, inputs, parameters):
        self.master = Master(step=0.5, progress=False)
        feed = self.master.add(Feed(inputs))
        fmu = self.master.add(FmuComponent(path, interface=interface, name="fmu",
                                           parameters=parameters))
        for name in inputs:
            self.master.connect(feed, name, fmu, name)

    def run(self, steps, dt):
        self.master.run(self.master.time + steps * dt)

    def close(self):
        self.master.finish()


def bench_fmu(path, interface, inputs, parameters, steps: int, rounds: int) -> dict:
    """Median CPU/wall us per step of bare fmpy, component and master, alternated."""
    kinds = {"bare_fmpy": lambda: BareFmpy(path, inputs, parameters),
             "component": lambda: ComponentOnly(path, interface, inputs, parameters),
             "master": lambda: MasterRun(path, interface, inputs, parameters)}
    cpu = {k: [] for k in kinds}
    wall = {k: [] for k in kinds}
    for round_index in range(rounds):
        order = list(kinds)
        order = order[round_index % 3:] + order[:round_index % 3]  # no fixed first place
        for kind in order:
            runner = kinds[kind]()
            runner.run(50, 0.5)  # warm up (first calls, caches)
            w, c = _timed(lambda: runner.run(steps, 0.5))
            runner.close()
            cpu[kind].append(c / steps * 1e6)
            wall[kind].append(w / steps * 1e6)
    median = {k: statistics.median(v) for k, v in cpu.items()}
    per_round = {k: [m / b for m, b in zip(cpu[k], cpu["bare_fmpy"])]
                 for k in ("component", "master")}
    return {
        "us_per_step": median,
        "wall_us_per_step": {k: statistics.median(v) for k, v in wall.items()},
        "master_over_bare": median["master"] / median["bare_fmpy"],
        "component_over_bare": median["component"] / median["bare_fmpy"],
        "master_over_bare_per_round": [min(per_round["master"]), max(per_round["master"])],
        "component_over_bare_per_round": [min(per_round["component"]),
                                          max(per_round["component"])],
        "meets_target": (median["master"] / median["bare_fmpy"] <= TARGET_MASTER
                         and median["component"] / median["bare_fmpy"] <= TARGET_COMPONENT),
    }


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

        runs = [_timed(run) for _ in range(5)]
        result[f"{method}_us_per_particle_step"] = \
            min(r[1] for r in runs) / (steps * particles) * 1e6
        result[f"{method}_wall_us_per_particle_step"] = \
            min(r[0] for r in runs) / (steps * particles) * 1e6
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=5000, help="FMU steps per timing (5000)")
    parser.add_argument("--rounds", type=int, default=7,
                        help="alternated rounds per FMU; medians are over these (7)")
    parser.add_argument("--particles", type=int, default=20000,
                        help="particles in the mill operator timing (20000, the paper's pile)")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.particles < 1 or args.rounds < 1:
        print("bench_fmu: error: --steps, --rounds and --particles must be >= 1", file=sys.stderr)
        return 2
    load_before = os.getloadavg()
    result = {"load_average_before": list(load_before), "cpu_count": os.cpu_count(),
              "steps": args.steps, "rounds": args.rounds,
              "target_master_over_bare": TARGET_MASTER,
              "target_component_over_bare": TARGET_COMPONENT, "fmu": {},
              "note": "us_per_step: median over alternated rounds of process CPU time per "
                      "communication step; wall_us_per_step is inflated when other processes "
                      "share the cores"}
    print(f"load average {load_before[0]:.2f} {load_before[1]:.2f} {load_before[2]:.2f} "
          f"on {os.cpu_count()} cores", file=sys.stderr)
    for path, interface, inputs, parameters in _cases():
        print(f"timing {path.name} ...", file=sys.stderr)
        result["fmu"][path.name] = bench_fmu(path, interface, inputs, parameters, args.steps,
                                             args.rounds)
        entry = result["fmu"][path.name]
        print(f"  master/bare {entry['master_over_bare']:.2f}, component/bare "
              f"{entry['component_over_bare']:.2f}", file=sys.stderr)
    result["load_average_after"] = list(os.getloadavg())
    print(f"load average {result['load_average_after'][0]:.2f}", file=sys.stderr)
    print("timing mill operator ...", file=sys.stderr)
    operator = bench_mill_operator(args.particles)
    operator["particles"] = args.particles
    operator["target_us_per_particle_step"] = 1.0
    operator["meets_target"] = operator["exponential_us_per_particle_step"] < 1.0
    operator["note"] = ("us_per_particle_step is process CPU time (best of 5); wall time is "
                        "also given and is inflated when other processes share the cores")
    result["mill_operator"] = operator
    result["meets_targets"] = all(e["meets_target"] for e in result["fmu"].values())
    print(jsonio.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
