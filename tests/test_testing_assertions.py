"""The assertion helpers and tolerance bands of minetwin.testing, on synthetic signals."""

import numpy as np
import pandas as pd
import pytest

from cosim.errors import ValidationError
from minetwin.testing.assertions import (
    account_ids, assert_ids_accounted, assert_mass_balance, assert_signal_within_band,
    assert_step_response, measure_step_response)
from minetwin.testing.bands import Tolerance, compare_signal

T = np.linspace(0.0, 100.0, 401)            # s, 0.25 s samples
REF = 1000.0 + 200.0 * np.sin(T / 8.0)      # W, a power-like signal


# ------------------------------------------------------------------ bands
def test_identical_signal_passes_a_zero_width_band():
    comparison = compare_signal("p", T, REF, T, REF, Tolerance(0.0, 0.0, 0.0))
    assert comparison.passed and comparison.worst_deviation == 0.0


def test_relative_and_absolute_tolerance_set_the_band_height():
    assert compare_signal("p", T, REF * 1.009, T, REF, Tolerance(rtol=0.01)).passed
    assert not compare_signal("p", T, REF * 1.011, T, REF, Tolerance(rtol=0.01)).passed
    assert compare_signal("p", T, REF + 4.9, T, REF, Tolerance(atol=5.0, rtol=0.0)).passed
    comparison = compare_signal("p", T, REF + 5.1, T, REF, Tolerance(atol=5.0, rtol=0.0))
    assert not comparison.passed
    assert comparison.n_outside == T.size
    assert comparison.worst_deviation == pytest.approx(5.1)


def test_time_shift_is_allowed_up_to_the_band_width():
    late = 1000.0 + 200.0 * np.sin((T - 1.0) / 8.0)   # the same signal, 1 s late
    inner = T >= 1.0                                   # the reference has no past before 0
    assert not compare_signal("p", T[inner], late[inner], T, REF, Tolerance(0, 0, 0.5)).passed
    assert compare_signal("p", T[inner], late[inner], T, REF, Tolerance(0, 0, 1.0)).passed


def test_band_uses_reference_samples_inside_the_window_not_only_its_ends():
    # a narrow spike in the reference: a result at the spike's height, shifted
    # within the window, is inside the band although the window's ends are low
    t_ref = np.array([0.0, 1.0, 1.1, 1.2, 3.0])
    y_ref = np.array([0.0, 0.0, 10.0, 0.0, 0.0])
    band = Tolerance(0, 0, 0.5)
    assert compare_signal("spike", [0, 1.5, 3], [0, 10, 0], t_ref, y_ref, band).passed
    late = compare_signal("spike", [0, 1.7, 3], [0, 10, 0], t_ref, y_ref, band)
    assert not late.passed and late.worst_time == 1.7


def test_window_extremes_match_a_brute_force_evaluation():
    rng = np.random.default_rng(3)
    t_ref = np.cumsum(rng.uniform(0.05, 1.0, 300))
    y_ref = rng.normal(size=300)
    t = np.linspace(t_ref[0], t_ref[-1], 500)
    y = np.interp(t, t_ref, y_ref) + rng.normal(scale=0.3, size=t.size)
    comparison = compare_signal("x", t, y, t_ref, y_ref, Tolerance(atol=0.1, rtol=0.05,
                                                                   time_shift=0.7))
    for k in range(0, t.size, 7):
        lo, hi = max(t[k] - 0.7, t_ref[0]), min(t[k] + 0.7, t_ref[-1])
        grid = np.concatenate([[lo, hi], t_ref[(t_ref >= lo) & (t_ref <= hi)]])
        window = np.interp(grid, t_ref, y_ref)
        allowance = 0.1 + 0.05 * np.abs(window).max()
        assert comparison.lower[k] == pytest.approx(window.min() - allowance)
        assert comparison.upper[k] == pytest.approx(window.max() + allowance)


def test_nan_in_the_result_fails_and_short_runs_are_reported():
    y = REF.copy()
    y[100] = np.nan
    comparison = compare_signal("p", T, y, T, REF, Tolerance(rtol=0.5))
    assert not comparison.passed and comparison.worst_time == T[100]
    short = compare_signal("p", T[:200], REF[:200], T, REF, Tolerance(rtol=0.5))
    assert not short.passed
    assert "run the scenario at least as long as the reference (--until 100)" in short.message()


def test_band_failure_message_names_time_value_reference_and_band():
    y = REF.copy()
    y[200:] += 50.0                                     # a step change from t = 50 s
    with pytest.raises(AssertionError) as info:
        assert_signal_within_band(T, y, T, REF, rtol=0.02, time_shift=1.0,
                                  name="crusher.power")
    message = str(info.value)
    assert "signal 'crusher.power' leaves its tolerance band" in message
    assert "atol=0, rtol=0.02, time shift ±1 s" in message
    assert "t = 50" in message and "allowed [" in message and "record a new reference" in message


def test_bad_tolerance_and_bad_series_are_refused():
    with pytest.raises(ValidationError, match="rtol: must be a finite number >= 0"):
        Tolerance(rtol=-0.1)
    with pytest.raises(ValidationError, match="as many values as time points"):
        compare_signal("p", T, REF[:-1], T, REF)
    with pytest.raises(ValidationError, match="non-decreasing"):
        compare_signal("p", T[::-1], REF, T, REF)


# ------------------------------------------------------------------ mass balance
def test_mass_balance_passes_and_reports_a_lost_kilogram_with_its_time():
    assert assert_mass_balance({"mass_in_kg": 3000.0, "mass_held_kg": 1000.0,
                                "mass_out_kg": 2000.0}) == 0.0
    frame = pd.DataFrame({"mass_in_kg": [100.0, 200.0, 300.0],
                          "mass_held_kg": [100.0, 150.0, 99.0],
                          "mass_out_kg": [0.0, 50.0, 200.0]},
                         index=pd.Index([1.0, 2.0, 3.0], name="time"))
    with pytest.raises(AssertionError) as info:
        assert_mass_balance(frame, where="stockpile")
    message = str(info.value)
    assert message.startswith("mass balance of stockpile broken at t = 3 s")
    assert "1 kg lost" in message and "held 99 kg" in message


def test_mass_balance_names_a_missing_key():
    with pytest.raises(ValidationError, match="mass_out_kg: must be given"):
        assert_mass_balance({"mass_in_kg": 1.0, "mass_held_kg": 1.0})


# ------------------------------------------------------------------ ids
def test_ids_lost_duplicated_and_unknown_are_each_named():
    entered = [1, 2, 3, 4, 5]
    assert assert_ids_accounted(entered, held=[1, 2], left=[3, 4, 5]).ok
    with pytest.raises(AssertionError) as info:
        assert_ids_accounted(entered, held=[1, 2], left=[2, 4, 5, 9], kind="particle id",
                             where="crusher")
    message = str(info.value)
    assert "crusher: of 5 particle ids that entered" in message
    assert "1 particle id(s) lost (entered, but neither held nor left): 3" in message
    assert "1 particle id(s) duplicated (counted more than once): 2" in message
    assert "without ever entering: 9" in message


def test_split_tracking_ids_are_checked_by_mass():
    entered, entered_mass = [10, 11], [500.0, 400.0]
    account = account_ids(entered, held=[10], left=[10, 11, 11], entered_mass=entered_mass,
                          held_mass=[100.0], left_mass=[400.0, 300.0, 100.0],
                          split_allowed=True)
    assert account.ok
    with pytest.raises(AssertionError, match=r"partly lost \(mass missing\): 11: 100 kg"):
        assert_ids_accounted(entered, held=[10], left=[10, 11], entered_mass=entered_mass,
                             held_mass=[100.0], left_mass=[400.0, 300.0], split_allowed=True)
    with pytest.raises(AssertionError, match=r"more mass out than in \(applied twice\?\): 10"):
        assert_ids_accounted(entered, held=[10], left=[10, 10, 11], entered_mass=entered_mass,
                             held_mass=[100.0], left_mass=[400.0, 400.0, 400.0],
                             split_allowed=True)


# ------------------------------------------------------------------ step response
def _first_order(t, step_time, before, after, delay, tau):
    rise = np.clip(t - step_time - delay, 0.0, None)
    return before + (after - before) * (1.0 - np.exp(-rise / tau))


def test_step_response_gain_ratio_and_delay_are_measured():
    t = np.arange(0.0, 800.0, 0.5)
    clean = _first_order(t, 350.0, 1500.0, 2100.0, delay=40.0, tau=10.0)
    response = assert_step_response(t, clean, step_time=350.0, before=(100, 350),
                                    after=(500, 800), ratio=(1.35, 1.45), gain=(590, 610),
                                    delay=(45, 50))
    assert response.ratio == pytest.approx(1.4)
    # 50 % of a first-order rise after a dead time: delay + tau ln 2 (0.5 s samples)
    assert response.delay == pytest.approx(40.0 + 10.0 * np.log(2), abs=0.5)
    # the truck cycle on top: smoothing over one period removes it, so the
    # measured delay is that of the smoothed clean response, not an early crest
    cycle = 150.0 * np.sin(2 * np.pi * t / 55.0)
    kwargs = dict(step_time=350.0, before=(350 - 5 * 55, 350), after=(500, 500 + 5 * 55))
    smoothed_clean = measure_step_response(t, clean, smoothing=55.0, **kwargs)
    with_cycle = measure_step_response(t, clean + cycle, smoothing=55.0, **kwargs)
    assert with_cycle.ratio == pytest.approx(1.4, abs=0.01)
    assert with_cycle.delay == pytest.approx(smoothed_clean.delay, abs=1.0)
    # without smoothing a crest of the cycle crosses the threshold early
    unsmoothed = measure_step_response(t, clean + cycle, **kwargs).delay
    assert unsmoothed < smoothed_clean.delay - 3.0


def test_step_response_outside_bounds_says_what_was_measured():
    t = np.arange(0.0, 800.0, 0.5)
    y = _first_order(t, 350.0, 1500.0, 1650.0, delay=5.0, tau=5.0)
    with pytest.raises(AssertionError) as info:
        assert_step_response(t, y, step_time=350.0, before=(100, 350), after=(500, 800),
                             ratio=(1.25, 1.55), name="crusher.power")
    message = str(info.value)
    assert "step response of 'crusher.power' to the step at t = 350 s" in message
    assert "ratio after/before 1.1 outside [1.25, 1.55]" in message
    assert "level 1500 before" in message


def test_a_response_that_never_arrives_has_infinite_delay():
    t = np.arange(0.0, 100.0, 1.0)
    response = measure_step_response(t, np.where(t < 90, 1.0, 2.0), step_time=10.0,
                                     before=(0, 10), after=(95, 100))
    assert response.delay == 80.0
    flat = measure_step_response(t, np.ones_like(t), step_time=10.0,
                                 before=(0, 10), after=(50, 90))
    assert flat.delay == np.inf


def test_undefined_reference_samples_must_stay_undefined():
    t = np.arange(10.0)
    ref = np.where(t < 4, np.nan, 1.0)          # a sensor over an empty asset, then defined
    tol = Tolerance(rtol=0.01, time_shift=1.0)
    assert compare_signal("s", t, ref, t, ref, tol).passed
    # NaN one sample later is within the allowed time shift
    assert compare_signal("s", t, np.where(t < 5, np.nan, 1.0), t, ref, tol).passed
    early = compare_signal("s", t, np.where(t < 1, np.nan, 1.0), t, ref, tol)
    assert not early.passed and early.worst_time == 1.0   # defined where the reference is not
    late = compare_signal("s", t, np.where(t < 7, np.nan, 1.0), t, ref, tol)
    assert not late.passed and late.n_outside == 2        # t = 5, 6 undefined, reference not
