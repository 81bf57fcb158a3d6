"""Master-side comminution operators: the crusher's fragmentation map and the
mill population balance (default exponential integrator: stable, positive,
mass-conserving for any step; the paper's explicit update: correct for small
steps, unstable above its limit)."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import fmu_reference as ref
from cosim.comminution import (EXPLICIT_SAFETY, apply_fragmentation, explicit_step_limit,
                               integrator_for, mill_step, mill_step_mass)
from cosim.errors import ValidationError

UNIFORM_DAUGHTERS = np.array([[1.0 / j if i < j else 0.0 for j in range(16)] for i in range(16)])
ROOT = Path(__file__).resolve().parent.parent


def _particles(n=50, seed=0):
    rng = np.random.default_rng(seed)
    f = rng.dirichlet(np.ones(16), n)
    return f, rng.uniform(10.0, 200.0, n), rng.uniform(1.0, 2.0, n)


def _rates(scale=1.0, k_esc=1000.0):
    d = 1e-5 * (10 ** (1 / 3)) ** np.arange(16)
    rate = scale * np.r_[0.0, np.linspace(0.5, 20.0, 15)]
    escape = k_esc / (1 + np.exp(np.minimum(10 * (d / 2.5e-5 - 1), 700)))
    return rate, escape


def test_fragmentation_map_applied_per_particle():
    f, _, _ = _particles()
    fmap = ref.crusher(np.zeros(16), 10.0)["fragmentation_map"]
    out = apply_fragmentation(f, fmap)
    for row_in, row_out in zip(f, out):
        expected = [sum(fmap[i][j] * row_in[j] for j in range(16)) for i in range(16)]
        np.testing.assert_allclose(row_out, expected, rtol=1e-13, atol=1e-16)
    np.testing.assert_allclose(out.sum(axis=1), 1.0, rtol=1e-13)
    assert np.all(out[:, 14:] == 0.0)  # nothing at or above the 0.25 m gap


def test_fragmentation_map_that_loses_mass_is_refused():
    fmap = np.eye(16)
    fmap[3, 3] = 0.9
    with pytest.raises(ValidationError, match="fragmentation_map: must be columns summing to 1"):
        apply_fragmentation(np.full(16, 1 / 16), fmap)


def test_explicit_update_is_the_papers_formula():
    f, mass, hardness = _particles(20)
    rate, escape = _rates()
    dt = 2e-4
    new_f, new_mass, escaped = mill_step(f, mass, hardness, rate, UNIFORM_DAUGHTERS, escape, dt,
                                         method="explicit")
    for n in range(len(mass)):
        x, out = ref.mill_explicit_step(list(f[n] * mass[n]), hardness[n], rate,
                                        UNIFORM_DAUGHTERS.tolist(), escape, dt)
        np.testing.assert_allclose(new_f[n] * new_mass[n], x, rtol=1e-12, atol=1e-12)
        assert escaped[n] == pytest.approx(out, rel=1e-12)


@settings(max_examples=40, deadline=None)
@given(dt=st.floats(1e-6, 1e4), scale=st.floats(0.0, 1e3), k_esc=st.floats(0.0, 1e5),
       seed=st.integers(0, 1000))
def test_exponential_is_positive_and_conserves_mass_for_any_step(dt, scale, k_esc, seed):
    f, mass, hardness = _particles(30, seed)
    rate, escape = _rates(scale, k_esc)
    new_f, new_mass, escaped = mill_step(f, mass, hardness, rate, UNIFORM_DAUGHTERS, escape, dt)
    np.testing.assert_allclose(new_mass + escaped, mass, rtol=1e-12)
    assert np.all(new_mass >= 0.0) and np.all(escaped >= 0.0)
    assert np.all(new_f >= 0.0)
    np.testing.assert_allclose(new_f.sum(axis=1), 1.0, rtol=1e-12)


def test_exponential_converges_to_analytic_two_class_solution():
    # only class 1 breaks (rate a, into class 0), class 0 escapes at q:
    # x1 = exp(-a t), x0 = a/(q - a) (exp(-a t) - exp(-q t))
    a, q, horizon = 3.0, 40.0, 1.0
    rate = np.zeros(16)
    rate[1] = a
    escape = np.zeros(16)
    escape[0] = q
    start = np.zeros((1, 16))
    start[0, 1] = 1.0
    exact0 = a / (q - a) * (math.exp(-a * horizon) - math.exp(-q * horizon))
    errors = []
    for n in (4, 8, 16, 32, 64):
        x, escaped = mill_step_mass(start, 1.0, rate, UNIFORM_DAUGHTERS, escape, horizon,
                                    substeps=n)
        assert x[0, 1] == pytest.approx(math.exp(-a * horizon), rel=1e-12)  # exact decay
        errors.append(abs(x[0, 0] - exact0))
        assert x.sum() + escaped.sum() == pytest.approx(1.0, rel=1e-13)
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert np.all(ratios > 1.8), ratios  # at least first-order convergence


def test_hardness_divides_the_breakage_rate():
    f, mass, _ = _particles(10)
    rate, escape = _rates()
    hard = mill_step(f, mass, 2.0, rate, UNIFORM_DAUGHTERS, escape, 0.3)
    soft = mill_step(f, mass, 1.0, rate / 2.0, UNIFORM_DAUGHTERS, escape, 0.3)
    for a, b in zip(hard, soft):
        np.testing.assert_allclose(a, b, rtol=1e-13)


def test_escape_is_reported_per_particle_in_input_order():
    f = np.zeros((3, 16))
    f[0, 0] = 1.0    # fines: escape at ~k_esc
    f[1, 12] = 1.0   # coarse, no breakage: cannot escape
    f[2, 1] = 1.0
    rate = np.zeros(16)
    _, escape = _rates()
    _, new_mass, escaped = mill_step(f, np.array([10.0, 20.0, 30.0]), 1.0, rate,
                                     UNIFORM_DAUGHTERS, escape, 0.01)
    assert escaped[0] == pytest.approx(10.0 * (1 - math.exp(-escape[0] * 0.01)), rel=1e-12)
    assert escaped[1] == 0.0 and new_mass[1] == 20.0
    assert escaped[2] == pytest.approx(30.0 * (1 - math.exp(-escape[1] * 0.01)), rel=1e-12)


def test_explicit_update_fails_above_its_limit_and_default_does_not():
    f, mass, hardness = _particles(5)
    rate, escape = _rates()  # k_esc = 1000/s: limit 2 / 1000 s
    for dt, method in ((5e-3, "explicit"), (5e-3, "exponential"), (5e-4, "explicit")):
        x, _ = mill_step_mass(f * mass[:, None], hardness, rate, UNIFORM_DAUGHTERS, escape,
                              0.5, method=method, substeps=int(round(0.5 / dt)))
        if dt > 2e-3 and method == "explicit":
            assert np.max(np.abs(x)) > 1e6 * mass.max()  # diverged: masses of huge magnitude
        else:
            assert np.min(x) >= 0.0 and np.all(x.sum(axis=1) <= mass)


def test_auto_takes_the_explicit_update_only_inside_its_limit():
    f, mass, hardness = _particles(5)
    rate, escape = _rates()
    limit = explicit_step_limit(hardness, rate, escape)
    assert limit == pytest.approx(1.0 / max(rate / hardness.min() + escape))
    x = f * mass[:, None]
    for dt, expected in ((0.9 * EXPLICIT_SAFETY * limit, "explicit"),
                         (1.1 * EXPLICIT_SAFETY * limit, "exponential"), (0.5, "exponential")):
        assert integrator_for(dt, hardness, rate, escape) == expected
        auto = mill_step_mass(x, hardness, rate, UNIFORM_DAUGHTERS, escape, dt, method="auto")
        chosen = mill_step_mass(x, hardness, rate, UNIFORM_DAUGHTERS, escape, dt, method=expected)
        assert all(np.array_equal(a, b) for a, b in zip(auto, chosen))
        assert np.min(auto[0]) >= 0.0
        assert np.allclose(auto[0].sum(axis=1) + auto[1].sum(axis=1), mass, rtol=1e-12)
    assert explicit_step_limit(hardness, np.zeros(16), np.zeros(16)) == float("inf")


def test_bad_operator_input_is_refused_with_the_field_named():
    f, mass, hardness = _particles(3)
    rate, escape = _rates()
    coarsening = UNIFORM_DAUGHTERS.copy()
    coarsening[:, 5] = 0.0
    coarsening[7, 5] = 1.0
    cases = [
        (dict(daughter_fraction=coarsening), "daughter_fraction: must be zero on and below"),
        (dict(hardness=-1.0), "hardness: must be finite and > 0"),
        (dict(breakage_rate=-rate), "breakage_rate: must be finite and >= 0 1/s"),
        (dict(dt=0.0), "dt: must be finite and > 0 s"),
        (dict(method="rk4"), "method: must be one of"),
    ]
    for override, message in cases:
        kwargs = dict(f=f, mass=mass, hardness=hardness, breakage_rate=rate,
                      daughter_fraction=UNIFORM_DAUGHTERS, escape_rate=escape, dt=0.1)
        kwargs.update(override)
        with pytest.raises(ValidationError, match=message):
            mill_step(**kwargs)


def test_stability_example_writes_chart(tmp_path):
    from cosim.fmu import fmu_path
    from fmus.build import build_all

    build_all(["crusher", "mill"])
    spec = importlib.util.spec_from_file_location(
        "mill_integrator_stability", ROOT / "examples" / "mill_integrator_stability.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    assert fmu_path("mill").is_file()
    result = example.study([1e-3, 1e-2, 0.1, 1.0], horizon=1.0, fine_step=2e-5)
    assert result["stability_limit_s"] == pytest.approx(2e-3, rel=0.05)
    explicit, exponential = result["explicit"], result["exponential"]
    assert explicit[0] < 1e-3 and all(e is None or e > 1.0 for e in explicit[1:])
    # bounded: even one step over the whole horizon misplaces < 20 % of the mass
    assert all(e < 0.2 for e in exponential)
    assert exponential[0] < exponential[1] < exponential[2] < exponential[3]
    assert example.main(["--out", str(tmp_path), "--horizon", "0.2"]) == 0
    assert (tmp_path / "mill_integrator_stability.png").stat().st_size > 10_000
