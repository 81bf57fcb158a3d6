"""Every figure function of the project follows cosim.plotstyle.

Each one is called with small inputs of the shape its analysis produces; the
figure is read through ``plotstyle.SAVE_HOOKS`` (its matplotlib artists, not
the PNG) and must have a title, a [unit] on every axis label that has tick
labels, a legend entry for every line, and (for runs) the scenario, seed and
storage model in its title.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from cosim import plotstyle

ROOT = Path(__file__).resolve().parents[1]
RUN = plotstyle.run_label({"simulation": {"seed": 7},
                           "assets": {"pile": {"kind": "stockpile", "model": "fifo"}}},
                          scenario="unit_test")


@pytest.fixture
def figures():
    """Figures saved while the test runs: path -> (problems, suptitle text, figure)."""
    seen = {}

    def hook(fig, path):
        title = fig._suptitle.get_text() if fig._suptitle else ""
        seen[Path(path).name] = (plotstyle.problems(fig), title, fig)

    plotstyle.SAVE_HOOKS.append(hook)
    yield seen
    plotstyle.SAVE_HOOKS.remove(hook)


def _axis_labels(fig):
    return [label for ax in fig.axes for label in (ax.get_xlabel(), ax.get_ylabel()) if label]


def _check(figures, names, run=RUN):
    assert sorted(figures) == sorted(names)
    for name in names:
        found, title, fig = figures[name]
        assert found == [], (name, found)
        if run is not None:
            assert run in title, (name, title)
        # one unit per quantity, as in the monitor: grade in %, hardness relative [-]
        for label in _axis_labels(fig):
            if "grade" in label.lower():
                assert "[%]" in label, (name, label)
            if "hardness" in label.lower():
                assert "[-]" in label, (name, label)


def _series(t, **columns):
    return pd.DataFrame(columns, index=pd.Index(t, name="time"))


def test_run_label_names_scenario_seed_and_model():
    assert RUN == "scenario unit_test, seed 7, storage model fifo"
    assert plotstyle.run_label(scenario="x", seed=3, model="dem") == \
        "scenario x, seed 3, storage model dem"


def test_problems_finds_what_a_figure_lacks():
    plt = plotstyle.pyplot()
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    ax.set_xlabel("time")
    found = plotstyle.problems(fig)
    assert "no title" in found
    assert any("x label 'time' has no [unit]" in p for p in found)
    assert any("y label '' has no [unit]" in p for p in found)
    assert any("is in no legend" in p for p in found)
    plt.close(fig)


def test_step_response_figures(figures, tmp_path):
    from cosim.analyses.step_response import plot

    t = np.arange(0.0, 800.0, 1.0)
    hard = (t > 350).astype(float)
    step = _series(t, **{"crusher_fmu.power": 3e3 + 1e3 * hard,
                         "crusher.zone_mass_kg": 500 + 10 * np.sin(t),
                         "crusher.zone_hardness": 1 + hard, "crusher.zone_hardness_avg": 1 + hard,
                         "mill_fmu.power": 3e5 + 1e5 * (t > 600), "mill.hardness": 1 + (t > 600),
                         "mill.hardness_avg": 1 + (t > 600), "mill.mass_kg": 2e4 + 0 * t})
    reference = step.assign(**{"mill_fmu.power": 3e5 + 0 * t, "mill.hardness": 1 + 0 * t,
                               "mill.hardness_avg": 1 + 0 * t})
    summary = {"hard_ore_reached_s": 350.0, "crusher_power_before_w": 3e3,
               "crusher_power_after_w": 4e3, "crusher_power_ratio": 4 / 3,
               "truck_cycle_period_s": 55.0, "discharge_start_s": 500.0,
               "mill_hardness_rise_time_s": 100.0, "mill_power_ratio_vs_reference": 1.33}
    plot(step, reference, summary, tmp_path, 30.0, run=RUN)
    _check(figures, ["crusher_step.png", "mill_step.png"])
    # the crusher-zone mass (right axis) and the 350 s line are in the legend
    crusher = figures["crusher_step.png"][2]
    texts = [t.get_text() for t in crusher.axes[0].get_legend().get_texts()]
    assert "mass in crusher zone (right axis)" in texts
    assert "hard ore reaches the crusher (350 s)" in texts
    mill = figures["mill_step.png"][2]
    assert "stockpile discharge starts (500 s)" in [
        t.get_text() for t in mill.axes[1].get_legend().get_texts()]


def test_overview_does_not_exaggerate_a_flat_hardness(figures, tmp_path):
    from cosim.scenario import plot_overview

    t = np.arange(0.0, 600.0, 1.0)
    series = _series(t, **{"crusher_fmu.power": 3e3 + 0 * t,
                           "crusher.zone_hardness_avg": 1 + 0 * t,
                           "stockpile.mass_kg": 1e3 * t, "mill_fmu.power": 3e5 + 0 * t,
                           "mill.hardness_avg": 1 + 7e-4 * t / 600})
    plot_overview(series, tmp_path / "overview.png", run=RUN)
    _check(figures, ["overview.png"])
    twin = figures["overview.png"][2].axes[-1]
    low, high = twin.get_ylim()
    assert high - low >= 0.5  # a 0.07 % rise is drawn nearly flat


def test_reference_overlay(figures, tmp_path):
    from minetwin.testing.bands import Tolerance, compare_signal
    from minetwin.testing.reference import plot_comparison

    t = np.arange(0.0, 100.0, 1.0)
    comparison = compare_signal("mill_fmu.power", t, 3e5 * (1 + 0.05 * (t > 50)), t,
                                3e5 + 0 * t, Tolerance())
    plot_comparison(comparison, tmp_path, RUN)
    _check(figures, ["mill_fmu.power.png"])
    ax = figures["mill_fmu.power.png"][2].axes[0]
    assert ax.get_ylabel() == "mill_fmu.power [W]"
    # the legend sits below the axes, never over the band
    assert ax.get_legend().get_bbox_to_anchor().y1 < ax.get_window_extent().y0


def test_integration_figures_show_every_source(figures, tmp_path):
    from minetwin.commands.integration import _plots

    rows = [{"time_s": float(k), "held_mass_kg": 1e3 * k, "grade": 0.2} for k in range(10)]
    log = [{"time_s": float(k), "by_source": {"0": 500.0}} for k in range(5, 10)]
    # bins 1 and 2 of source 0 and bin 3 of source 1 entered; only source 0's ore has left
    ledger = {"outflow_log": log, "source_of": {"1": 0, "2": 0, "3": 1},
              "delivered_by_source": {"0": 1e3}, "time_s": 10.0}
    _plots(tmp_path, ledger, {"history": rows, "model": "fifo", "seed": 0})
    _check(figures, ["stockpile_mass_grade.png", "cv301_composition.png"],
           run="seed 0, storage model fifo")
    texts = [t.get_text() for t in
             figures["cv301_composition.png"][2].axes[0].get_legend().get_texts()]
    assert texts == ["source 0: 2.5 t", "source 1: 0.0 t"]
    # with the names the plant's feed lots give (opcua_server.config.source_names)
    figures.clear()
    _plots(tmp_path, ledger, {"history": rows, "model": "fifo", "seed": 0},
           {0: "left source", 1: "right source"})
    texts = [t.get_text() for t in
             figures["cv301_composition.png"][2].axes[0].get_legend().get_texts()]
    assert texts == ["left source: 2.5 t", "right source: 0.0 t"]
    # a stockpile that lagged: 0.5 t reported after the clock stopped at 10 s is marked
    figures.clear()
    late = {**ledger, "outflow_log": log + [{"time_s": 10.0, "by_source": {"1": 500.0}}]}
    _plots(tmp_path, late, {"history": rows, "model": "fifo", "seed": 0})
    _check(figures, ["stockpile_mass_grade.png", "cv301_composition.png"],
           run="seed 0, storage model fifo")
    texts = [t.get_text() for t in
             figures["cv301_composition.png"][2].axes[0].get_legend().get_texts()]
    assert texts == ["source 0: 2.5 t", "source 1: 0.5 t", "end of the run; right of it: the "
                     "totals, with 0.5 t reported after the end (the stockpile lagged)"]
    # right of the end line the stack is as high as the totals (3.0 t)
    stack = figures["cv301_composition.png"][2].axes[0].collections[-1]
    top = stack.get_paths()[0].vertices
    assert top[:, 1].max() == pytest.approx(3.0) and top[:, 0].max() == pytest.approx(10.3)
    # the whole run, with room to see the step of the reports stamped at its end
    # (9.0 s is the last row here, so nothing is marked)
    assert figures["cv301_composition.png"][2].axes[0].get_xlim() == (0.0, pytest.approx(10.3))


def test_grindability_figures_explain_the_bwi_scale(figures, tmp_path):
    from cosim.analyses.grindability import BWI_NOTE, plot

    times = np.arange(100.0, 400.0, 30.0)
    data = {"signals": pd.DataFrame({"time": np.arange(0.0, 400.0, 30.0),
                                     "bwi_kwh_t": np.linspace(0.1, 0.12, 14)}),
            "result": {"times": times, "block_grindability": np.full((times.size, 3), 9.0),
                       "final": np.array([9.0, 9.5, 10.0]), "prior": np.array([9.5])},
            "index": np.array([0, 1, 2]), "hardness": np.array([1.0, 1.2, 1.4]),
            "enough": np.array([True, True, False])}
    plot(data, tmp_path, RUN)
    _check(figures, ["grindability.png", "block_grindability.png"])
    texts = [t.get_text() for t in figures["grindability.png"][2].axes[0].texts]
    assert BWI_NOTE in texts and "10-20 kWh/t" in BWI_NOTE


def test_mwd_figures(figures, tmp_path):
    from cosim.analyses import mwd
    from cosim.analyses.profile_run import SCENARIO

    x = np.linspace(0, 100, 50)
    run = SimpleNamespace(
        config={"simulation": {"seed": 7},
                "assets": {"stockpile": {"kind": "stockpile", "model": "fifo"}}},
        survey=pd.DataFrame({"source": "left", "x": x, "mwd": (1 + x / 100) ** 0.4}),
        profiles={"left": lambda at: 1 + np.asarray(at) / 100})
    times = np.arange(0.0, 300.0, 1.0)
    zone = pd.DataFrame({"time": times, "hardness_true": 1 + times / 300,
                         "hardness_beta_0.4": 1 + times / 300,
                         "hardness_beta_0.42": 1 + times / 310})
    data = {"times": times, "torque": 100 + times, "zone": zone,
            "models": {0.4: 100 + times}, "fit": SimpleNamespace(beta=0.4)}
    mwd.plot(run, data, {"beta_true": 0.4}, tmp_path)
    _check(figures, ["hardness_vs_mwd_tracking_error.png", "crusher_observed_torque_models.png",
                     "crusher_torque_to_hardness.png"],
           run=f"scenario {Path(SCENARIO).stem}, seed 7, storage model fifo")
    # the torque legend sits below the axes, not over the first truck load
    ax = figures["crusher_observed_torque_models.png"][2].axes[0]
    assert ax.get_legend().get_window_extent().y1 < ax.get_window_extent().y0


def test_sensitivity_figure(figures, tmp_path):
    from cosim.analyses.sensitivity import plot

    dx = np.repeat([0.0, 5.0, 10.0], 2)
    mwd_sweep = pd.DataFrame({"dx": dx, "beta_error": dx / 100})
    grind_sweep = pd.DataFrame({"dx": dx, "corr": -0.9 + dx / 100, "rel_deviation": dx / 50})
    plot(mwd_sweep, grind_sweep, tmp_path, RUN)
    _check(figures, ["sensitivity.png"])


def test_feed_prediction_figures(figures, tmp_path):
    from cosim.analyses.feed_prediction import plot

    t = np.arange(0.0, 100.0, 1.0)
    frame = pd.DataFrame({"time": t, "grade": 0.5 + 0 * t, "hardness": 1.2 + 0 * t})
    curves = {m: {"averages": frame, "outflow": frame, "predicted": frame, "realised": frame}
              for m in ("fifo", "rom")}
    rng = np.random.default_rng(0)
    spatial = pd.DataFrame({"x": rng.uniform(0, 10, 50), "y": rng.uniform(0, 5, 50),
                            "speed": rng.uniform(0, 1, 50), "grade": rng.uniform(0, 1, 50),
                            "hardness": rng.uniform(1, 2, 50)})
    ordered = pd.DataFrame({"x": np.zeros(50), "y": np.zeros(50), "speed": np.zeros(50),
                            "grade": rng.uniform(0, 1, 50), "hardness": rng.uniform(1, 2, 50),
                            "time_to_leave_s": np.linspace(0, 100, 50), "mass": np.full(50, 1e2)})
    for snap in (spatial, ordered):
        snap.attrs["time"] = 80.0
    plot(curves, {"rom": spatial, "fifo": ordered}, tmp_path, RUN)
    _check(figures, ["pile_distribution.png", "storage_evolution_and_outflow.png"])
    # the shaded horizon of a model without geometry is explained in each panel's title
    shaded = [ax for ax in figures["pile_distribution.png"][2].axes if ax.patches
              and ax.get_xlabel() == "expected time to leave [s]"]
    assert len(shaded) == 3
    assert all("grey: the feed of the next 30 s" in ax.get_title() for ax in shaded)


def test_dem_pile_pictures(figures, tmp_path):
    from surrogate.dem.plots import PICTURES, pile_pictures

    rng = np.random.default_rng(1)
    n = 40
    snapshot = {"position": rng.uniform(0, 2, (n, 2)), "radius": np.full(n, 0.05),
                "velocity": rng.normal(0, 0.1, (n, 2)), "grade": rng.uniform(0, 1, n),
                "residence_time": rng.uniform(0, 9, n), "time": 3.0}
    run = plotstyle.run_label(scenario="dem pile", seed=0, model="dem")
    pile_pictures(snapshot, tmp_path, run=run)
    _check(figures, [f"pile_{stem}.png" for stem in PICTURES], run=run)


def _example(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_example_figures(figures, tmp_path):
    from surrogate.rom import doe

    stability = _example("mill_integrator_stability")
    stability.plot({"steps_s": [0.01, 0.1, 1.0], "explicit": [1e-6, 1e-3, None],
                    "exponential": [1e-7, 1e-5, 1e-3], "stability_limit_s": 0.2,
                    "horizon_s": 60.0, "fine_step_s": 1e-4}, tmp_path / "stability.png")
    ladder = _example("speed_vs_accuracy")
    points = [{"kind": "fifo", "label": "FIFO", "wall_s_per_simulated_s": 1e-4,
               "tracking_error": 0.6},
              {"kind": "rom_dem", "label": "ROM 4/4 (default)", "modes": [4, 4],
               "wall_s_per_simulated_s": 1e-2, "tracking_error": 0.2},
              {"kind": "dem", "label": "DEM 2", "dt_factor": 2.0,
               "wall_s_per_simulated_s": 10.0, "tracking_error": 0.05},
              {"kind": "dem_nonsmooth", "label": "nonsmooth DEM 11 ms, 100 sweeps",
               "setting": "11 ms, 100 sweeps", "wall_s_per_simulated_s": 2.0,
               "tracking_error": 0.1},
              {"kind": "dem_nonsmooth", "label": "nonsmooth DEM 20 ms, 10 sweeps",
               "setting": "20 ms, 10 sweeps", "wall_s_per_simulated_s": 0.5, "unstable": True,
               "unstable_at_s": 12.0, "tracking_error": None}]
    ladder.plot_ladder({"points": points, "dem_noise_floor": 0.04,
                        "reference_wall_s_per_simulated_s": 20.0, "reference_dt_factor": 1.0,
                        "scenario": doe.HELDOUT_SCENARIOS[0].name}, tmp_path / "ladder.png")
    from surrogate.rom.grid import Grid

    grid = Grid(x_min=-2.0, x_max=2.0, y_min=0.0, y_max=2.0, nx=8, ny=4)
    rng = np.random.default_rng(2)
    fields = {"mass": rng.uniform(0, 1, (4, 8)), "velocity": rng.normal(0, 0.1, (4, 8, 2)),
              "grade": rng.uniform(0, 1, (4, 8)), "hardness": rng.uniform(1, 2, (4, 8))}
    ladder.plot_fields({"DEM": fields, "ROM (default modes)": fields}, grid, 30.0,
                       "heldout", tmp_path / "pile_fields.png")
    _check(figures, ["stability.png", "ladder.png", "pile_fields.png"], run=None)
    assert "storage models DEM and ROM (default modes)" in figures["pile_fields.png"][1]


def test_fidelity_chart_shows_the_target_every_model_and_the_timeline(figures, tmp_path):
    from cosim.fidelity_plot import plot_fidelity

    compared = [{"model": m, "holds": m != "mixing", "tracking_error": e, "noise_floor": 0.16,
                 "wall_s_per_s": c, "rows": ["heldout"]}
                for m, e, c in (("fifo", 0.9, 3e-5), ("mixing", 0.56, 9e-5), ("rom", 0.17, 1e-3),
                                ("dem", 0.16, 1.1))]
    point = {"throughput_kg_s": 400.0, "held_mass_kg": 9e4, "window_s": 30.0}
    switches = [{"time_s": 120.0, "from_model": "rom", "to_model": "dem", "reason": "x"}]
    run = {"model": "rom", "reason": "r", "target": {"tracking_error": 0.3},
           "operating_point": point, "compared": compared, "switches": switches}
    t = np.arange(0.0, 300.0, 1.0)
    series = _series(t, **{"pile.model_rung": np.where(t < 120.0, 2.0, 3.0)})
    plot_fidelity(run, tmp_path / "fidelity_pile.png", series=series, pile="pile", run=RUN)
    plot_fidelity({**run, "target": {"wall_s_per_s": 0.01}}, tmp_path / "budget.png")
    for name in ("fidelity_pile.png", "budget.png"):
        found, title, fig = figures[name]
        assert found == [], (name, found)
        labels = [text.get_text() for ax in fig.axes if ax.get_legend()
                  for text in ax.get_legend().get_texts()]
        assert "chosen: rom" in labels and "mixing (card does not hold here)" in labels
        assert any(label.startswith("DEM noise floor") for label in labels)
    assert RUN in figures["fidelity_pile.png"][1]
    _, _, fig = figures["fidelity_pile.png"]
    timeline = fig.axes[1]
    assert [t.get_text() for t in timeline.get_yticklabels()] == \
        ["0: fifo", "1: mixing", "2: rom", "3: dem"]
    assert "target: tracking error <= 0.3" in [
        t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert "budget: 0.01 wall s per simulated s" in [
        t.get_text() for t in figures["budget.png"][2].axes[0].get_legend().get_texts()]


def test_coupling_step_figure(figures, tmp_path):
    from cosim.analyses.coupling_step import coupling_errors, largest_step_within, plot

    t = np.arange(1.0, 301.0, 1.0)
    runs = {h: _series(t, **{"crusher_fmu.power": 1e3 + 50 * np.sin(t / 20) + 100 * h})
            for h in (0.25, 0.5, 1.0)}
    table = coupling_errors(runs, ["crusher_fmu.power"], window_s=60.0, until=300.0)
    plot(table, {0.25: 0.01, 0.5: 0.006, 1.0: 0.004}, 0.1, largest_step_within(table, 0.1),
         tmp_path / "coupling_step.png", run=RUN)
    _check(figures, ["coupling_step.png"])
