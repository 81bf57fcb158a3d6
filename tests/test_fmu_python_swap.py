"""Swap (b): a user-written Python crusher, packaged as an FMI 2.0 FMU with
pythonfmu inside the test, runs through the same master and scenario as our
C FMUs; an FMU lacking a required variable is refused with a clear error."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from cosim.fmu import CRUSHER_INTERFACE, FmuComponent, FmuInterfaceError, fmu_path
from fmu_scenario import run_crusher_scenario

pythonfmu = pytest.importorskip("pythonfmu", reason="pythonfmu is a test extra (pip install -e .[test])")

USER_CRUSHER = '''
from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Integer, Real

DIAMETERS = [1e-5 * (10 ** (1 / 3)) ** k for k in range(16)]


class UserJawCrusher(Fmi2Slave):
    """The paper's jaw crusher written by a user in Python."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.gap_width = 0.25
        self.speed = 10.0
        self.torque = self.power = self.energy = 0.0
        self.zone = [0.0] * 16
        self.register_variable(Real("gap_width", causality=Fmi2Causality.parameter,
                                    variability=Fmi2Variability.fixed))
        self.register_variable(Real("speed", causality=Fmi2Causality.input))
        for k in range(16):
            self.register_variable(Real(f"zone_hardness_mass[{k + 1}]", causality=Fmi2Causality.input,
                                        getter=lambda k=k: self.zone[k],
                                        setter=lambda v, k=k: self.zone.__setitem__(k, v)))
        for name in OUTPUTS:
            self.register_variable(Real(name, causality=Fmi2Causality.output))
        if INTEGER_ENERGY:
            self.register_variable(Integer("energy", causality=Fmi2Causality.output,
                                           getter=lambda: int(self.energy)))
        for i in range(16):
            for j in range(16):
                self.register_variable(Real(f"fragmentation_map[{i + 1},{j + 1}]",
                                            causality=Fmi2Causality.output,
                                            getter=lambda i=i, j=j: self.map_entry(i, j)))

    def map_entry(self, i, j):
        over = [d >= self.gap_width for d in DIAMETERS]
        if over[j]:
            return 0.0 if over[i] else 1.0 / over.count(False)
        return 1.0 if i == j else 0.0

    def do_step(self, current_time, step_size):
        self.torque = sum((1.0 if d >= self.gap_width else 0.1) * m
                          for d, m in zip(DIAMETERS, self.zone))
        self.power = self.torque * self.speed
        self.energy += self.power * step_size
        return True
'''


def _build(tmp_path, outputs, integer_energy=False):
    from pythonfmu.builder import FmuBuilder

    script = tmp_path / "user_jaw_crusher.py"
    script.write_text(textwrap.dedent(USER_CRUSHER).replace("OUTPUTS", repr(outputs))
                      .replace("INTEGER_ENERGY", repr(integer_energy)))
    return FmuBuilder.build_FMU(script, dest=tmp_path)


def test_user_python_fmu_runs_through_same_master(tmp_path):
    path = _build(tmp_path, ("torque", "power", "energy"))
    user, user_zone = run_crusher_scenario(path)
    ours, our_zone = run_crusher_scenario(fmu_path("crusher", 2))
    assert list(user.columns) == list(ours.columns)
    np.testing.assert_allclose(user.to_numpy(), ours.to_numpy(), rtol=1e-12)
    np.testing.assert_allclose(user_zone.f, our_zone.f, rtol=1e-12, atol=1e-15)


def test_user_fmu_lacking_a_variable_is_refused(tmp_path):
    path = _build(tmp_path, ("torque", "power"))
    with pytest.raises(FmuInterfaceError) as info:
        FmuComponent(path, interface=CRUSHER_INTERFACE)
    assert str(info.value) == (
        "UserJawCrusher.fmu: variable 'energy': must be an output Float64 variable, "
        "a scalar (missing)")


def test_user_fmu_with_wrongly_typed_variable_is_refused(tmp_path):
    path = _build(tmp_path, ("torque", "power"), integer_energy=True)
    with pytest.raises(FmuInterfaceError, match="variable 'energy': must be an output Float64 "
                                                "variable, a scalar \\(its type is Integer\\)"):
        FmuComponent(path, interface=CRUSHER_INTERFACE)
