"""The paper's step-response mechanism (section "Results", "Step response"), --quick size."""

import json

import pytest

from cosim.analyses.step_response import checks, dominant_period, reproduce


def test_dominant_period_finds_the_alternating_truck_cycle():
    import numpy as np

    t = np.arange(0.0, 600.0, 0.5)
    dumps = (t % 27.5) < 15.0                       # a dump every 27.5 s
    hard = (t % 55.0) < 27.5                        # every other dump is twice as hard
    assert dominant_period(t, dumps * 1.0) == pytest.approx(27.5, abs=0.6)
    assert dominant_period(t, dumps * np.where(hard, 2.0, 1.0)) == pytest.approx(55.0, abs=0.6)


@pytest.mark.slow
def test_step_response_shows_the_papers_mechanism(tmp_path):
    summary, failed = reproduce(tmp_path, quick=True, progress=False)
    assert failed == [] == checks(summary)
    assert 1.25 <= summary["crusher_power_ratio"] <= 1.55
    assert summary["truck_cycle_period_s"] == pytest.approx(55.0, abs=5.0)
    assert summary["hard_ore_reached_s"] == pytest.approx(350.0)
    assert summary["mill_power_ratio_vs_reference"] > 1.0
    assert 0.0 < summary["mill_hardness_rise_time_s"] < 250.0
    assert summary["mass_balance_rel_error"] < 1e-9
    assert json.loads((tmp_path / "summary.json").read_text())["crusher_power_ratio"] == \
        summary["crusher_power_ratio"]
    for name in ("crusher_step.png", "mill_step.png"):
        assert (tmp_path / name).stat().st_size > 10_000


@pytest.mark.slow
def test_the_declared_paper_plant_gives_the_step_response_figures_of_the_fixed_one(tmp_path):
    """examples/step_response.toml as a declared plant gives the figures the fixed
    topology gave (examples/README.md, "Paper vs ours": `minetwin reproduce step-response`,
    seed 1, FIFO, 1,200 s): crusher power ratio 1.49, mill hardness rise 101 s."""
    summary, failed = reproduce(tmp_path, quick=False, progress=False)
    assert failed == []
    assert round(summary["crusher_power_ratio"], 2) == 1.49
    assert summary["mill_hardness_rise_time_s"] == pytest.approx(101.0, abs=0.5)
    assert summary["mass_balance_rel_error"] < 1e-9
