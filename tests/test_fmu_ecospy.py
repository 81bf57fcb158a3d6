"""Cross-check with an independent FMI master: the same FMU stepped by our
master (fmpy low-level API) and by ecospy (the Ecos co-simulation engine, C++)
gives the same outputs for the same inputs."""

from __future__ import annotations

import ctypes
import sys
from pathlib import Path

import numpy as np
import pytest

from cosim.fmu import CRUSHER_INTERFACE, MILL_INTERFACE, FmuComponent, fmi2_scalar_names, fmu_path


def _ecospy():
    # ecospy's engine links libtbb.so.12; the pinned `tbb` test extra ships it in the
    # environment's lib/, which the loader does not search: load it first by path.
    bundled = Path(sys.prefix) / "lib" / "libtbb.so.12"
    if bundled.is_file():
        ctypes.CDLL(str(bundled), mode=ctypes.RTLD_GLOBAL)
    try:
        import ecospy
    except ImportError as exc:
        pytest.skip(f"ecospy is not installed ({exc}); it is a test extra: pip install -e .[test]")
    except OSError as exc:  # its bundled engine needs the TBB runtime
        pytest.skip(f"ecospy cannot load its engine here ({exc}); install the test extras "
                    "(pip install -e .[test], which brings tbb) or apt-get install libtbb12")
    return ecospy


@pytest.fixture(scope="module", autouse=True)
def built_fmus():
    from fmus.build import build_all

    build_all()


def _inputs(model, k):
    rng = np.random.default_rng(100 + k)
    if model == "crusher":
        return {"speed": 10.0 + k % 3, "zone_hardness_mass": rng.gamma(1.0, 50.0, 16)}
    return {"speed_setpoint": [1.2, 0.9, 1.4][k % 3], "charge_mass": rng.gamma(1.0, 100.0, 16)}


@pytest.mark.parametrize("model,interface", [("crusher", CRUSHER_INTERFACE),
                                             ("mill", MILL_INTERFACE)])
def test_ecospy_and_our_master_agree(model, interface):
    ecospy = _ecospy()
    path = fmu_path(model, 2)  # ecospy addresses FMI 2.0 scalars by name
    dt, steps = 0.5, 12
    structure = ecospy.EcosSimulationStructure()
    structure.add_model("m", str(path))
    sim = ecospy.EcosSimulation(structure=structure, step_size=dt)
    ours = FmuComponent(path, interface=interface)
    try:
        sim.init()
        for k in range(steps):
            for name, value in _inputs(model, k).items():
                ours.set_input(name, value)
                if np.ndim(value) == 0:
                    sim.set_real(f"m::{name}", float(value))
                else:
                    for i, v in enumerate(value):
                        sim.set_real(f"m::{name}[{i + 1}]", float(v))
            ours.step(k * dt, dt)
            sim.step()
            assert sim.get_time() == pytest.approx((k + 1) * dt)
            out = ours.outputs()
            for spec in interface:
                if spec.causality != "output":
                    continue
                if spec.shape == ():
                    theirs = sim.get_real(f"m::{spec.name}")
                else:
                    theirs = np.array([sim.get_real(f"m::{n}")
                                       for n in fmi2_scalar_names(spec.name, spec.shape)]
                                      ).reshape(spec.shape)
                np.testing.assert_array_equal(out[spec.name], theirs, err_msg=spec.name)
    finally:
        ours.finish()
        sim.terminate()
        sim.free()
