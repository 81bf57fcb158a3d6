"""The ROM stockpile end to end over OPC UA (the paper's integration test with the ROM).

``minetwin integration-test --model rom --option model=PATH`` starts the mock
800xA server and the stockpile client (running ``RomStorage`` from the model
file) as real processes on 127.0.0.1; the audit of the server's ledger
against the client's final state must find every tracking id and every
kilogram. A plain ``minetwin integration-test`` does the same with the shipped
paper-scale ROM and a pre-filled pile.

The ROM is trained here on synthetic but physical data: heaps of random height
and shape with the 2-D point-sink funnel flow towards the outlet,
|v| = q / (rho_A pi r) inside the pile.
"""

import json

import numpy as np
import pytest

from minetwin.cli import main
from surrogate.rom.container import Container
from surrogate.rom.grid import Grid, mass_field
from surrogate.rom.model import RomModel

CONTAINER = Container(x_min=-10.0, x_max=10.0, floor=0.0, outlet_x=0.0, inlet_x=0.0,
                      areal_density=1600.0, repose_angle=0.6)
GRID = Grid.covering(-10.0, 10.0, 0.0, 8.0, 1.0)
SETPOINT_KG_S = 200.0
"""Discharge-rate setpoint of the mock server's default configuration [kg/s]."""
PARTICLE_MASS_KG = 100.0
"""Largest pseudo-particle mass of ``minetwin stockpile`` (its default) [kg]."""
DISCHARGE_START_S = 30.0
"""The server's setpoint is 0 until then (``sp201.discharge_start_s``): the pile fills
first (CV101 is 40 m at 2 m/s: the first bin arrives after 20 s)."""


def synthetic_rom(samples: int = 40, seed: int = 1) -> RomModel:
    """A ROM trained on random triangular heaps with the point-sink funnel flow."""
    rng = np.random.default_rng(seed)
    x, y = GRID.centres()
    centres = np.column_stack([g.ravel() for g in np.meshgrid(x, y)])
    lattice_x, lattice_y = (g.ravel() for g in np.meshgrid(np.arange(-9.8, 10, 0.4),
                                                            np.arange(0.2, 8, 0.4)))
    masses, velocities, q_out, q_in = [], [], [], []
    for _ in range(samples):
        height, centre = rng.uniform(4, 7.5), rng.uniform(-2, 2)
        inside = lattice_y < height - CONTAINER.repose_angle * np.abs(lattice_x - centre)
        position = np.column_stack((lattice_x[inside], lattice_y[inside]))
        field = mass_field(GRID, position, np.full(len(position), 0.16 * CONTAINER.areal_density))
        rate = rng.uniform(0, 400)
        offset = centres - [CONTAINER.outlet_x, CONTAINER.floor]
        r = np.maximum(np.linalg.norm(offset, axis=1), 0.5)
        sink = -rate / (CONTAINER.areal_density * np.pi * r)[:, None] * offset / r[:, None]
        masses.append(field)
        velocities.append(sink.reshape(GRID.ny, GRID.nx, 2) * (field > 0)[..., None])
        q_out.append(rate)
        q_in.append(rng.uniform(0, 300))
    return RomModel(GRID, n_mass_modes=6, n_velocity_modes=6, ridge=1e-3,
                    container=CONTAINER).fit(np.array(masses), np.array(q_out), np.array(q_in),
                                             np.array(velocities))


@pytest.fixture(scope="module")
def rom_file(tmp_path_factory):
    return synthetic_rom().save(tmp_path_factory.mktemp("rom") / "synthetic.rom.npz")


@pytest.mark.slow
def test_rom_stockpile_over_opcua_loses_nothing_and_discharges(rom_file, tmp_path):
    out = tmp_path / "run"
    duration = 60.0
    config = tmp_path / "plant.toml"
    config.write_text(f"[sp201]\ndischarge_start_s = {DISCHARGE_START_S}\n")
    code = main(["integration-test", "--duration", str(duration), "--speed", "3",
                 "--model", "rom", "--option", f"model={rom_file}",
                 "--option", "update_interval=2", "--config", str(config),
                 "--out", str(out), "--no-monitor"])
    report = json.loads((out / "report.json").read_text())
    assert code == 0, report
    # the stockpile process ran the ROM from this file, with both options
    assert report["model"] == report["stockpile_model"] == "rom"
    assert report["storage_options"] == {"model": str(rom_file), "update_interval": 2}
    assert "stockpile: model rom" in (out / "stockpile.log").read_text()
    # an empty pile is outside the synthetic heaps' range: only the ROM checks that
    assert any(w.startswith("OutOfTrainingRange: ROM input held_mass")
               for w in report["stockpile_warnings"])
    # nothing lost, nothing counted twice, every kilogram accounted for
    assert report["duration_s"] == pytest.approx(duration)  # plant time, whatever the lag
    assert report["bins_in"] >= 35
    assert report["tracking_ids_lost"] == 0 and report["tracking_ids_duplicated"] == 0
    assert report["mass_balance_rel_error"] < 1e-9 and report["unsent_reports"] == 0
    # the ROM's feeder really discharged bins: nothing before the scheduled
    # start of the discharge (the setpoint node read 0), never more than the
    # setpoint allows since then (the credit rule, plus at most one particle),
    # and at the setpoint once it runs (inflow 250 kg/s > setpoint, so it does
    # not run dry; the ROM takes whole particles, hence 10 %)
    # (how many reports carry it depends on the wall-clock pacing: a stockpile
    # lagging 18 s under load caught up in 2; the kilograms do not)
    assert report["outflow_reports"] >= 1
    assert 0 < report["mass_out_kg"] <= (SETPOINT_KG_S * (report["duration_s"] - DISCHARGE_START_S)
                                         + PARTICLE_MASS_KG)
    log = json.loads((out / "ledger.json").read_text())["outflow_log"]
    assert log[0]["time_s"] >= DISCHARGE_START_S
    # on the stockpile's own plant clock (the server stamps a report when the
    # exchange cycle that carries it runs, later when the stockpile lags): the
    # pile only fills before the start, and the feeder runs at the setpoint after
    history = json.loads((out / "stockpile.summary.json").read_text())["history"]
    before = [row["held_mass_kg"] for row in history if row["time_s"] <= DISCHARGE_START_S]
    assert before == sorted(before)
    rate = report["mass_out_kg"] / (report["duration_s"] - DISCHARGE_START_S)
    assert rate == pytest.approx(SETPOINT_KG_S, rel=0.1)


@pytest.mark.slow
def test_the_default_integration_test_is_the_papers_prefilled_rom_stockpile(tmp_path):
    """A plain ``minetwin integration-test``: the shipped paper-scale ROM with its
    DEM surface layer, 1,500 t in the pile at the start, every bin and kilogram
    accounted for. Invariants only (the surface layer is a DEM): the audit, and
    the feeder's credit rule, which holds whatever the pile's flow."""
    out = tmp_path / "run"
    code = main(["integration-test", "--duration", "30", "--speed", "2", "--out", str(out),
                 "--no-monitor"])
    report = json.loads((out / "report.json").read_text())
    assert code == 0, report
    assert report["model"] == report["stockpile_model"] == "rom"
    assert report["storage_options"] == {}  # the shipped model, no file given
    prefill_bins = 1_500_000.0 / 250.0  # prefilled.toml in CV101's 250 kg bins
    assert report["bins_in"] >= prefill_bins + 1
    assert report["tracking_ids_lost"] == 0 and report["tracking_ids_duplicated"] == 0
    assert report["mass_balance_rel_error"] < 1e-9 and report["unsent_reports"] == 0
    # the pile never runs dry, so the feeder takes the setpoint to within a particle
    assert abs(report["mass_out_kg"] - SETPOINT_KG_S * report["duration_s"]) <= PARTICLE_MASS_KG


def test_bad_rom_option_is_refused_by_name_before_any_process_starts(tmp_path, capsys):
    out = tmp_path / "run"
    for option, field in ((f"model={tmp_path / 'missing.npz'}", "model"),
                          ("no_such_option=1", "option.no_such_option"), ("model", "option")):
        code = main(["integration-test", "--duration", "10", "--model", "rom",
                     "--option", option, "--out", str(out)])
        assert code == 2
        assert capsys.readouterr().err.splitlines()[-1].startswith(
            f"minetwin integration-test: error: {field}:")
    assert not out.exists()
